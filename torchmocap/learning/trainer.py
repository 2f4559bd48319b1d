"""The training loop of learned likelihood terms (behind ``torchmocap-train``).

One network is trained on many clips: the term built from the config is *bound* to each clip's
body and rig (:meth:`~torchmocap.likelihoods.learned.LearnedLikelihood.bind`), all sharing its
``net``. The energy a frame is scored with is ``V = V_base + V_learned``: ``V_base`` the
hand-crafted likelihood of the negatives' tracker (``base: tracker``; fixed, not trained) or
nothing (``base: none``), or another likelihood preset (``base_likelihood: silhouette``), so the
learned term corrects the hand-crafted cost, replaces part of it, or replaces it — use it in
tracking the same way (``likelihood=silhouette_learned``, ``image_learned`` or ``learned``).

Per epoch: shuffled batches of frames (a seeded generator), the objective's loss (ranking,
end to end, or both), optimiser step, LR schedule; then validation (ranking loss, pairwise
accuracy truth-vs-negatives, top-1 rate) on the validation clips; metrics appended to
``metrics.csv`` and TensorBoard; ``checkpoints/last.pt`` (and ``best.pt`` by validation loss)
written atomically; ``weights.pt`` (the best network) at the end.
"""

from __future__ import annotations

import csv
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from torchmocap.atomic import atomic_path
from torchmocap.learning.checkpoints import load_checkpoint, save_checkpoint
from torchmocap.learning.data import ClipData, pose_errors
from torchmocap.learning.objectives import (
    joint_error,
    ranking_loss,
    unrolled_annealing,
    unrolled_descent,
)
from torchmocap.likelihoods.base import Poses

__all__ = ["EndToEndSettings", "TrainSettings", "Trainer"]

OBJECTIVES = ("ranking", "end_to_end", "both")
OPTIMISERS = ("adam", "adamw", "sgd")
SCHEDULES = ("none", "cosine", "step")


@dataclass
class EndToEndSettings:
    """The end-to-end objective: unroll ``mode`` (``annealing`` or ``descent``) from a start
    drawn by the tracker's proposal at ``start_scale`` times its spread around the truth."""

    mode: str = "annealing"
    """``annealing`` (layers with stop-gradient resampling) or ``descent`` (Adam steps)."""
    particles: int = 48
    layers: int = 3
    """annealing: particles and layers unrolled."""
    steps: int = 5
    lr: float = 0.02
    """descent: steps and learning rate unrolled."""
    start_scale: float = 2.0
    """the start's spread, times the tracker proposal's own."""
    weight: float = 1.0
    """the end-to-end loss's weight beside the ranking loss (objective ``both``)."""


@dataclass
class TrainSettings:
    """Settings of :class:`Trainer` (the ``torchmocap-train`` config without data and term)."""

    objective: str = "ranking"
    """``ranking``, ``end_to_end`` or ``both``."""
    err_scale: float = 0.02
    err_rotation: float = 0.0
    """a candidate's error: joint error over ``err_scale`` metres plus ``err_rotation`` times
    its rotation error."""
    base: str = "tracker"
    """``tracker``: the term is trained on top of the tracker's own cost; ``none``: alone."""
    max_negatives: int = 32
    optimizer: str = "adam"
    """``adam``, ``adamw`` or ``sgd`` (:data:`OPTIMISERS`)."""
    lr: float = 3e-3
    weight_decay: float = 0.0
    schedule: str = "cosine"
    """learning-rate schedule: ``none``, ``cosine`` or ``step``."""
    grad_clip: float = 5.0
    """the gradient's largest norm (0: no clipping)."""
    batch_size: int = 8
    epochs: int = 10
    seed: int = 0
    device: str = "cpu"
    end_to_end: EndToEndSettings = field(default_factory=EndToEndSettings)

    def check(self) -> None:
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective.name: expected one of {OBJECTIVES}, got "
                             f"{self.objective!r}")
        if self.optimizer not in OPTIMISERS:
            raise ValueError(f"optim.name: expected one of {OPTIMISERS}, got {self.optimizer!r}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"optim.schedule: expected one of {SCHEDULES}, got "
                             f"{self.schedule!r}")
        if self.base not in ("tracker", "none"):
            raise ValueError(f"objective.base: expected 'tracker' or 'none', got {self.base!r}")
        if self.end_to_end.mode not in ("annealing", "descent"):
            raise ValueError(f"objective.end_to_end.mode: expected 'annealing' or 'descent', "
                             f"got {self.end_to_end.mode!r}")
        for k in ("batch_size", "epochs", "max_negatives"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{k}: expected a positive int, got {v!r}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"optim.lr: expected a positive number, got {self.lr!r}")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise ValueError(f"device: {self.device!r} requested but CUDA is not available")


def _to_device(clip: ClipData, device: torch.device) -> None:
    rt = clip.runtime
    for name in ("skeleton", "body", "rig"):
        m = getattr(rt, name)
        if m is not None and hasattr(m, "to"):
            setattr(rt, name, m.to(device))


def _frame_to(frame, device):
    import dataclasses

    return dataclasses.replace(frame, **{
        k: getattr(frame, k).to(device) for k in ("silhouettes", "view_dropped", "images")
        if isinstance(getattr(frame, k), torch.Tensor)})


class Trainer:
    """Train ``term`` (a :class:`~torchmocap.likelihoods.learned.LearnedLikelihood`) on
    ``train`` clips, validating on ``val`` clips (:func:`~torchmocap.learning.load_clip_set`).

    Args:
        term: the prototype term (its ``net`` is trained).
        train, val: lists of :class:`~torchmocap.learning.ClipData`.
        settings: :class:`TrainSettings`.
        out: output directory (``metrics.csv``, ``tb/``, ``checkpoints/``, ``weights.pt``).
        train_config: the resolved config, stored in checkpoints.
    """

    def __init__(self, term, train: list[ClipData], val: list[ClipData], settings: TrainSettings,
                 out: str | os.PathLike, train_config: dict | None = None,
                 tensorboard: bool = True, progress: bool = True,
                 base_likelihood: str | None = None) -> None:
        settings.check()
        if not train or not any(c.frames for c in train):
            raise ValueError("data.train_clips: no training frames")
        self.s = settings
        self.device = torch.device(settings.device)
        self.term = term.to(self.device)
        self.train_data, self.val_data = train, val
        for c in train + val:
            _to_device(c, self.device)
        self.terms = [term.bind(c.runtime.body, c.runtime.rig) for c in train]
        self.val_terms = [term.bind(c.runtime.body, c.runtime.rig) for c in val]
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.train_config = dict(train_config or {})
        self.progress = progress
        self.generator = torch.Generator().manual_seed(settings.seed)
        params = list(term.net.parameters())
        if settings.optimizer == "sgd":
            self.optimizer = torch.optim.SGD(params, lr=settings.lr, momentum=0.9,
                                             weight_decay=settings.weight_decay)
        elif settings.optimizer == "adamw":
            self.optimizer = torch.optim.AdamW(params, lr=settings.lr,
                                               weight_decay=settings.weight_decay)
        else:
            self.optimizer = torch.optim.Adam(params, lr=settings.lr,
                                              weight_decay=settings.weight_decay)
        n_frames = sum(len(c.frames) for c in train)
        self.steps_per_epoch = max(1, math.ceil(n_frames / settings.batch_size))
        total = max(1, self.steps_per_epoch * settings.epochs)
        if settings.schedule == "cosine":
            self.scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(self.optimizer, total)
        elif settings.schedule == "step":
            self.scheduler = torch.optim.lr_scheduler.StepLR(
                self.optimizer, max(1, total // 3), gamma=0.3)
        else:
            self.scheduler = None
        self.epoch, self.step = 0, 0
        self.metrics: list[dict] = []
        self.writer = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self.writer = SummaryWriter(str(self.out / "tb"))
            except ImportError:  # tensorboard not installed: CSV only, and say so
                import warnings

                warnings.warn("tensorboard is not installed: training metrics go to "
                              "metrics.csv only (pip install 'torchmocap[train]')", stacklevel=2)
                self.writer = None
        self._base_cache: dict[tuple[int, int, int], torch.Tensor] = {}
        self._base_liks: dict[int, Any] = {}
        self.base_likelihood = base_likelihood

    # ------------------------------------------------------------------ energies
    def base_of(self, clip: ClipData):
        """The clip's fixed hand-crafted likelihood: its tracker's, or the
        ``base_likelihood`` preset (a ``likelihood/`` config name) built for its runtime."""
        if self.base_likelihood is None:
            return clip.tracker.likelihood
        lik = self._base_liks.get(id(clip))
        if lik is None:
            from torchmocap.assembly import build_tracker, tracker_config

            cfg = tracker_config(clip.tracker.name, [
                f"likelihood@tracker.likelihood={self.base_likelihood}"])
            lik = build_tracker(cfg, clip.runtime).likelihood.to(self.device)
            self._base_liks[id(clip)] = lik
        return lik

    def _candidates(self, f, clip: ClipData) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([f.truth[None], f.negatives[:self.s.max_negatives]]).to(self.device)
        with torch.no_grad():
            err = pose_errors(clip.runtime.skeleton, x, f.truth.to(self.device),
                              self.s.err_rotation)
        return x, err

    def _base(self, clip: ClipData, frame, x: torch.Tensor, key=None) -> torch.Tensor | float:
        if self.s.base == "none":
            return 0.0
        if key is not None and key in self._base_cache:
            return self._base_cache[key]
        lik = self.base_of(clip)
        with torch.no_grad():
            v = lik.energy(Poses(x, clip.runtime.skeleton), lik.prepare(frame)).detach()
        if key is not None:
            self._base_cache[key] = v
        return v

    def energy_fn(self, term, clip: ClipData, frame):
        """``V(theta (P, D)) -> (P,)`` = base + learned for one frame (differentiable in the
        learned parameters and in ``theta``)."""
        obs = term.prepare(frame)
        base_lik = self.base_of(clip) if self.s.base == "tracker" else None
        base_obs = None if base_lik is None else base_lik.prepare(frame)
        sk = clip.runtime.skeleton

        def V(theta):
            v = term.energy(Poses(theta, sk), obs)
            if base_lik is not None:  # a value only: the hand-crafted energy (hard
                # silhouette) is not differentiable; it is not trained either
                with torch.no_grad():
                    b = base_lik.energy(Poses(theta.detach(), sk), base_obs)
                v = v + b.to(v.dtype)
            return v

        return V

    # ------------------------------------------------------------------ losses
    def frame_loss(self, ci: int, fi: int, train: bool = True) -> tuple[torch.Tensor, dict]:
        clips = self.train_data if train else self.val_data
        terms = self.terms if train else self.val_terms
        clip, term = clips[ci], terms[ci]
        f = clip.frames[fi]
        frame = _frame_to(f.frame, self.device)
        stats: dict[str, float] = {}
        loss = torch.zeros((), device=self.device)
        want_rank = self.s.objective in ("ranking", "both") or not train
        if want_rank:
            x, err = self._candidates(f, clip)
            obs = term.prepare(frame)
            v = term.energy(Poses(x, clip.runtime.skeleton), obs)
            v = v + self._base(clip, frame, x, (int(train), ci, fi))
            rl = ranking_loss(v, err, self.s.err_scale)
            loss = loss + rl
            with torch.no_grad():
                stats["ranking"] = float(rl)
                stats["pair_acc"] = float((v[1:] > v[0]).float().mean())
                stats["top1"] = float(v.argmin() == 0)
                if not train and self.s.base == "tracker":  # the hand-crafted energy alone
                    b = self._base(clip, frame, x, (0, ci, fi))
                    stats["base_ranking"] = float(ranking_loss(b, err, self.s.err_scale))
                    stats["base_pair_acc"] = float((b[1:] > b[0]).float().mean())
        if train and self.s.objective in ("end_to_end", "both"):
            e2e = self.s.end_to_end
            g = torch.Generator().manual_seed(self.s.seed * 1000003 + self.step * 101 + fi)
            ctx = self._context(clip, frame, f.truth.to(self.device), e2e.start_scale)
            with torch.no_grad():
                start = clip.tracker.proposal.sample(ctx, 1, g).particles[0]
            V = self.energy_fn(term, clip, frame)
            sk = clip.runtime.skeleton
            if e2e.mode == "descent":
                x = unrolled_descent(V, start[None], e2e.steps, e2e.lr, lower=sk.lower,
                                     upper=sk.upper)
                est = x[0]
            else:
                import dataclasses

                ctx0 = dataclasses.replace(ctx, previous=start, scale=1.0)
                est, _ = unrolled_annealing(V, clip.tracker.proposal, ctx0, e2e.particles,
                                            e2e.layers, generator=g)
            el = joint_error(sk, est, f.truth.to(self.device))
            loss = loss + e2e.weight * el
            stats["e2e_mm"] = 1000 * float(el.detach())
            stats["e2e_start_mm"] = 1000 * float(joint_error(sk, start, f.truth.to(self.device)))
        stats["loss"] = float(loss.detach())
        return loss, stats

    @staticmethod
    def _context(clip: ClipData, frame, truth, scale: float):
        from torchmocap.proposals.base import ProposalContext

        tr = clip.tracker
        return ProposalContext(previous=truth.to(tr.dtype), sensors=tr._sensors(frame),
                               sensor_valid=frame.imu_valid, frame=frame, scale=float(scale))

    # ------------------------------------------------------------------ loop
    def _order(self) -> list[tuple[int, int]]:
        items = [(ci, fi) for ci, c in enumerate(self.train_data) for fi in range(len(c.frames))]
        perm = torch.randperm(len(items), generator=self.generator).tolist()
        return [items[i] for i in perm]

    def validate(self) -> dict[str, float]:
        """Mean ranking loss, pairwise accuracy and top-1 rate over the validation frames."""
        acc: dict[str, list[float]] = {}
        with torch.no_grad():
            for ci, c in enumerate(self.val_data):
                for fi in range(len(c.frames)):
                    _, st = self.frame_loss(ci, fi, train=False)
                    for k, v in st.items():
                        acc.setdefault(k, []).append(v)
        return {f"val_{k}": sum(v) / len(v) for k, v in acc.items() if v}

    def resume(self, path: str | os.PathLike) -> None:
        """Continue from a checkpoint (weights, optimiser, schedule, data order, metrics)."""
        payload = load_checkpoint(path, self.term, optimizer=self.optimizer,
                                  scheduler=self.scheduler, generator=self.generator)
        if int(payload["epoch"]) >= self.s.epochs:
            raise ValueError(f"epochs: the checkpoint {path} has trained {payload['epoch']} "
                             f"epochs already; set epochs > {payload['epoch']} to go on")
        self.epoch, self.step = int(payload["epoch"]), int(payload["step"])
        self.metrics = list(payload.get("metrics") or [])

    def _write_csv(self) -> None:
        if not self.metrics:
            return
        keys: list[str] = []
        for m in self.metrics:
            keys += [k for k in m if k not in keys]
        with atomic_path(self.out / "metrics.csv") as tmp, open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys)
            w.writeheader()
            for m in self.metrics:
                w.writerow(m)

    def _save(self, name: str) -> Path:
        return save_checkpoint(self.out / "checkpoints" / name, self.term,
                               optimizer=self.optimizer, scheduler=self.scheduler,
                               epoch=self.epoch, step=self.step, generator=self.generator,
                               metrics=self.metrics, train_config=self.train_config)

    def fit(self) -> list[dict]:
        """Train until ``epochs``; returns the per-epoch metrics."""
        from tqdm import tqdm

        if self.epoch == 0 and not self.metrics and self.val_data:
            m0 = {"epoch": 0, "step": 0, "seconds": 0.0, **self.validate()}
            self.metrics.append(m0)
            self._log(m0)
            self._write_csv()
        best = min((m.get("val_ranking", math.inf) for m in self.metrics), default=math.inf)
        while self.epoch < self.s.epochs:
            t0 = time.perf_counter()
            order = self._order()
            self.term.train()
            sums: dict[str, float] = {}
            n = 0
            bar = tqdm(range(0, len(order), self.s.batch_size), disable=not self.progress,
                       desc=f"epoch {self.epoch + 1}/{self.s.epochs}", unit="batch")
            for a in bar:
                batch = order[a:a + self.s.batch_size]
                self.optimizer.zero_grad(set_to_none=True)
                for ci, fi in batch:
                    loss, st = self.frame_loss(ci, fi)
                    (loss / len(batch)).backward()
                    for k, v in st.items():
                        sums[k] = sums.get(k, 0.0) + v
                    n += 1
                if self.s.grad_clip > 0:
                    torch.nn.utils.clip_grad_norm_(self.term.net.parameters(), self.s.grad_clip)
                self.optimizer.step()
                if self.scheduler is not None:
                    self.scheduler.step()
                self.step += 1
                if self.writer is not None:
                    self.writer.add_scalar("train/loss", sums["loss"] / n, self.step)
                bar.set_postfix(loss=f"{sums['loss'] / n:.4f}")
            self.epoch += 1
            m: dict[str, Any] = {"epoch": self.epoch, "step": self.step,
                                 "seconds": time.perf_counter() - t0,
                                 "lr": self.optimizer.param_groups[0]["lr"],
                                 **{f"train_{k}": v / max(n, 1) for k, v in sums.items()}}
            if self.val_data:
                self.term.eval()
                m.update(self.validate())
            self.metrics.append(m)
            self._log(m)
            self._write_csv()
            self._save("last.pt")
            score = m.get("val_ranking", m.get("train_loss", math.inf))
            if score <= best:
                best = score
                self._save("best.pt")
        if self.writer is not None:
            self.writer.flush()
        return self.metrics

    def _log(self, m: dict) -> None:
        if self.writer is None:
            return
        for k, v in m.items():
            if k not in ("epoch", "step") and isinstance(v, (int, float)):
                group = "val" if k.startswith("val_") else "epoch"
                self.writer.add_scalar(f"{group}/{k}", v, int(m["epoch"]))

    def export(self, path: str | os.PathLike, which: str = "best") -> Path:
        """Write the ``best`` (by validation loss) or ``last`` network as a weights file
        (no optimiser state: small enough for a repository)."""
        from torchmocap.likelihoods.learned import read_weights, write_weights

        src = self.out / "checkpoints" / f"{which}.pt"
        if not src.is_file():
            src = self.out / "checkpoints" / "last.pt"
        p = read_weights(src)
        keep = {k: p[k] for k in ("term", "config", "state_dict")}
        keep["trained"] = {"epoch": int(p["epoch"]), "metrics": p.get("metrics", [])[-1:],
                           "train_config": p.get("train_config", {})}
        return write_weights(path, keep)
