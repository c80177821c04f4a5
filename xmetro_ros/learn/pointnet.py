"""The study's modified PointNet for per-point regression (PyTorch), and how point sets are formed.

Architecture (study §3.5, Fig. 2; no T-Net/STN): shared MLP block 1 on every point → shared MLP block 2 →
max-pool over the set → global feature, repeated for every point and concatenated with block 1's output → final
MLP (the "head") → linear output, one column per target axis. Loss: MAE; Adam with an adaptive learning rate
(ReduceLROnPlateau). The study layout is block1 (64, 64), block2 (64, 128, 1024), head of a 1088-wide input.

Spread head (``sigma_head=True``, the default family ``pointnet_multi``): a second MLP of the head's shape on the
same hidden layer outputs log σ per axis (σ in mm: the spread of the measured error around the prediction). Its
loss is the Gaussian negative log-likelihood of the *detached* residual, log σ + r² / (2σ²), added to the MAE: the
error head keeps the study's L1 objective (its gradient is not reweighted by σ, the failure mode of a joint NLL
fit), and σ learns E[r² | point] — the scale that split-conformal calibration then turns into a 95 % interval
(:mod:`xmetro_ros.learn.uncertainty`). Exported as the ONNX output ``log_sigma`` next to ``y``.

Input normalisation (feature mean/std) and the target scale are buffers inside the module, so the exported ONNX
graph maps raw features (study units) to errors in mm.

Point sets: the network sees *sets* of points of one cloud. In training, each epoch draws random sets of
``set_size`` points (without replacement) from each cloud's training points; in the test draws each cloud's points
form sets of the same size. At inference a whole scan is split deterministically into sets of ``set_size`` points
by a seeded permutation (:func:`partition_sets`); a last, shorter set is padded by repeating its own points, which
leaves the max-pooled global feature unchanged, and only the real entries are kept.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from ..judge.pointsets import partition_sets

__all__ = ["STUDY_LAYOUT", "PointNetConfig", "PointNetReg", "PointNetRegressor", "partition_sets", "sets_by_group"]


def _mlp(sizes: Sequence[int], final_relu: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if final_relu or i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class PointNetReg(nn.Module):
    """Set-to-points regressor. forward: (B, n, F) raw features → (B, n, n_out) errors in mm."""

    # registered buffers (normalisation), declared for the type checker
    x_mean: torch.Tensor
    x_std: torch.Tensor
    y_scale: torch.Tensor

    def __init__(
        self,
        n_features: int,
        block1: Sequence[int] = (64, 64),
        block2: Sequence[int] = (64, 128, 1024),
        head: Sequence[int] = (512, 256, 128),
        n_out: int = 1,
        sigma_head: bool = False,
    ) -> None:
        super().__init__()
        if not head:
            raise ValueError("the PointNet head needs at least one hidden layer")
        self.block1 = _mlp([n_features, *block1])
        self.block2 = _mlp([block1[-1], *block2])
        # First head layer on concat([f1, g]) written as W_l·f1 + W_g·g: the same function, but the global part
        # is computed once per set instead of once per point (the 1088-wide concat is never materialised).
        self.head_local = nn.Linear(block1[-1], head[0])
        self.head_global = nn.Linear(block2[-1], head[0], bias=False)
        self.head = _mlp([head[0], *head[1:], n_out], final_relu=False)
        self.head_sigma: nn.Module | None = _mlp([head[0], *head[1:], n_out], final_relu=False) if sigma_head else None
        self.register_buffer("x_mean", torch.zeros(n_features))
        self.register_buffer("x_std", torch.ones(n_features))
        self.register_buffer("y_scale", torch.ones(n_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """(B, n, F) → y (B, n, A) mm; with the spread head also log σ (B, n, A), σ in mm."""
        z = (x - self.x_mean) / self.x_std
        f1 = self.block1(z)
        g = self.block2(f1).amax(dim=1, keepdim=True)  # (B, 1, G): global feature of each set
        h = torch.relu(self.head_local(f1) + self.head_global(g))
        y = self.head(h) * self.y_scale
        if self.head_sigma is None:
            return y
        return y, self.head_sigma(h) + torch.log(self.y_scale)


STUDY_LAYOUT = {"block1": (64, 64), "block2": (64, 128, 1024), "head": (512, 256, 128)}


def sets_by_group(groups: np.ndarray, set_size: int, rng: np.random.Generator | int) -> tuple[np.ndarray, np.ndarray]:
    """Random sets of ``set_size`` points drawn without replacement within each group (cloud).

    Returns (idx (K, set_size) indices into ``groups``, real (K, set_size) bool). Groups are never mixed.
    """
    rng = np.random.default_rng(rng)
    groups = np.asarray(groups)
    order = np.argsort(groups, kind="stable")
    bounds = np.flatnonzero(np.diff(groups[order])) + 1
    all_idx, all_real = [], []
    for members in np.split(order, bounds):
        sub_idx, sub_real = partition_sets(len(members), set_size, int(rng.integers(2**31)))
        all_idx.append(members[sub_idx])
        all_real.append(sub_real)
    return np.concatenate(all_idx), np.concatenate(all_real)


@dataclass
class PointNetConfig:
    """Hyper-parameters of one PointNet fit."""

    block1: tuple[int, ...] = (64, 64)
    block2: tuple[int, ...] = (64, 128, 1024)
    head: tuple[int, ...] = (512, 256, 128)
    set_size: int = 50
    epochs: int = 150
    batch_sets: int = 4  # small batches: more updates per epoch (measured: better and faster than 16)
    lr: float = 2e-3
    weight_decay: float = 0.0
    patience: int = 8  # epochs without improvement before the learning rate is halved (adaptive rate)
    threads: int = 1  # torch threads: on a shared 2-core machine 2 threads were 10x slower than 1
    sigma_head: bool = False  # second head: log σ per axis (Gaussian NLL of the detached residual)
    extra: dict = field(default_factory=dict)


class PointNetRegressor:
    """Fit / predict wrapper around :class:`PointNetReg` with an sklearn-like API (groups = cloud ids)."""

    family = "pointnet"

    def __init__(self, config: PointNetConfig | None = None, seed: int = 0, warm_start: PointNetReg | None = None
                 ) -> None:
        """``warm_start``: a fitted network (same features, outputs and layer sizes) that ``fit`` starts from,
        keeping its input / target normalisation (fine-tuning a prior, e.g. a virtual scanner's model, on few
        recorded scans); it is copied, never modified."""
        self.config = config or PointNetConfig()
        self.seed = seed
        self.warm_start = warm_start
        self.module_: PointNetReg | None = None
        self.history_: list[float] = []

    def get_params(self) -> dict:
        c = self.config
        return {"block1": list(c.block1), "block2": list(c.block2), "head": list(c.head), "set_size": c.set_size,
                "epochs": c.epochs, "lr": c.lr, "sigma_head": c.sigma_head}

    def fit(self, X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> PointNetRegressor:
        """X (M, F) raw features, y (M,) or (M, A) mm, groups (M,) cloud ids (sets never mix clouds)."""
        X = np.asarray(X, np.float32)
        y2 = np.asarray(y, np.float32).reshape(len(X), -1)
        if len(X) == 0:
            raise ValueError("PointNet: no training points")
        c = self.config
        torch.manual_seed(self.seed)
        rng = np.random.default_rng(self.seed)
        prev_threads = torch.get_num_threads()
        torch.set_num_threads(max(1, c.threads))
        try:
            if self.warm_start is not None:
                net = copy.deepcopy(self.warm_start)
                if net.x_mean.numel() != X.shape[1] or (net.head_sigma is not None) != c.sigma_head:
                    raise ValueError("PointNet warm start: the network has other features or heads than the data")
            else:
                net = PointNetReg(X.shape[1], c.block1, c.block2, c.head, n_out=y2.shape[1], sigma_head=c.sigma_head)
                std = X.std(0)
                net.x_mean.copy_(torch.from_numpy(X.mean(0)))
                net.x_std.copy_(torch.from_numpy(np.where(std > 1e-12, std, 1.0).astype(np.float32)))
                ys = np.abs(y2 - np.median(y2, 0)).mean(0)
                net.y_scale.copy_(torch.from_numpy(np.where(ys > 1e-12, ys, 1.0).astype(np.float32)))
            opt = torch.optim.Adam(net.parameters(), lr=c.lr, weight_decay=c.weight_decay)
            sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=c.patience)
            Xt, yt = torch.from_numpy(X), torch.from_numpy(y2)
            best, best_state = np.inf, None
            for _epoch in range(c.epochs):
                idx, real = sets_by_group(groups, c.set_size, rng)
                order = rng.permutation(len(idx))
                total, count = 0.0, 0.0
                net.train()
                for start in range(0, len(order), c.batch_sets):
                    b = order[start : start + c.batch_sets]
                    bi, br = torch.from_numpy(idx[b]), torch.from_numpy(real[b]).float().unsqueeze(-1)
                    out = net(Xt[bi])
                    pred = out[0] if c.sigma_head else out
                    err = (pred - yt[bi]).abs() / net.y_scale * br
                    loss = err.sum() / (br.sum() * y2.shape[1])
                    if c.sigma_head:
                        # Gaussian NLL of the detached residual, in target-scale units (log σ − log y_scale).
                        ls = out[1] - torch.log(net.y_scale)
                        r = (pred.detach() - yt[bi]) / net.y_scale
                        nll = (ls + 0.5 * r**2 * torch.exp(-2 * ls)) * br
                        loss = loss + nll.sum() / (br.sum() * y2.shape[1])
                    opt.zero_grad()
                    loss.backward()
                    opt.step()
                    total += loss.item() * float(br.sum())
                    count += float(br.sum())
                epoch_loss = total / max(count, 1.0)
                self.history_.append(epoch_loss)
                sched.step(epoch_loss)
                if epoch_loss < best:
                    best, best_state = epoch_loss, copy.deepcopy(net.state_dict())
            if best_state is not None:
                net.load_state_dict(best_state)
            net.eval()
            self.module_ = net
        finally:
            torch.set_num_threads(prev_threads)
        return self

    def predict_sets(self, Xs: np.ndarray) -> np.ndarray:
        """(K, n, F) sets → (K, n, A) mm, float32 (the framework reference for ONNX checks)."""
        if self.module_ is None:
            raise RuntimeError("PointNetRegressor is not fitted")
        with torch.no_grad():
            out = self.module_(torch.from_numpy(np.asarray(Xs, np.float32)))
        return (out[0] if isinstance(out, tuple) else out).numpy()

    def predict_sets_sigma(self, Xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K, n, F) sets → (y (K, n, A) mm, σ (K, n, A) mm) float32; needs the spread head."""
        if self.module_ is None or self.module_.head_sigma is None:
            raise RuntimeError("PointNetRegressor has no fitted spread head (sigma_head=False)")
        with torch.no_grad():
            y, ls = self.module_(torch.from_numpy(np.asarray(Xs, np.float32)))
        return y.numpy(), np.exp(ls.numpy())

    def predict(self, X: np.ndarray, groups: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
        """Per-point predictions (M, A) mm; sets formed within each group by a seeded partition (see module doc)."""
        X = np.asarray(X, np.float32)
        groups = np.zeros(len(X), np.int64) if groups is None else np.asarray(groups)
        idx, real = sets_by_group(groups, self.config.set_size, seed)
        out = self.predict_sets(X[idx])
        pred = np.empty((len(X), out.shape[-1]), np.float32)
        pred[idx[real]] = out[real]
        return pred
