"""The selector's model: for every candidate grasp, the probability that it holds the object, from the
features at the decision point (`features.ChoiceFeatures`).

One small MLP with one sigmoid output per grasp, trained with binary cross-entropy on the
counterfactual labels (`labels.py`: every grasp was rolled out from the same decision state, so each
context labels every output; a grasp's output is masked where it was not rolled out). The choice is
the argmax: a discrete pick, never an average of two grasps' bytes. It runs in numpy (`bh8 deploy`
needs no torch); `fit` imports torch only while training.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

MAX_WIDTH = 4096  # units per layer a file may declare (policy files' own bound)
MAX_LAYERS = 8


class SuccessModel:
    """P(grasp k holds | features) for every k: `(x - mean) / std`, then tanh layers, then sigmoids."""

    def __init__(self, mean, std, weights: Sequence, biases: Sequence):
        self.mean = np.asarray(mean, dtype=np.float64)
        self.std = np.asarray(std, dtype=np.float64)
        self.weights = [np.asarray(w, dtype=np.float64) for w in weights]
        self.biases = [np.asarray(b, dtype=np.float64) for b in biases]
        self._check()

    def _check(self) -> None:
        if not 1 <= len(self.weights) <= MAX_LAYERS or len(self.biases) != len(self.weights):
            raise ValueError(f"a success model has 1 to {MAX_LAYERS} layers, each with weights and biases")
        width = self.mean.shape[0] if self.mean.ndim == 1 else -1
        if self.std.shape != self.mean.shape or width < 1:
            raise ValueError(f"the input scaling's mean {self.mean.shape} and std {self.std.shape} must be one vector")
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            if weight.ndim != 2 or weight.shape[0] != width or bias.shape != (weight.shape[1],) \
                    or not 1 <= weight.shape[1] <= MAX_WIDTH:
                raise ValueError(f"layer {index} has weights {weight.shape} and biases {bias.shape} after "
                                 f"{width} inputs: the layers do not chain")
            width = weight.shape[1]
        numbers = (self.mean, self.std, *self.weights, *self.biases)
        if not all(np.all(np.isfinite(a)) for a in numbers) or not np.all(self.std > 0):
            raise ValueError("a weight, bias or scaling of the success model is not finite (or a std not positive)")

    @property
    def inputs(self) -> int:
        return self.mean.shape[0]

    @property
    def outputs(self) -> int:
        return self.weights[-1].shape[1]

    def logits(self, features) -> np.ndarray:
        h = (np.asarray(features, dtype=np.float64) - self.mean) / self.std
        last = len(self.weights) - 1
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            h = h @ weight + bias
            if index < last:
                h = np.tanh(h)
        return h

    def __call__(self, features) -> np.ndarray:
        """Probabilities, one per grasp (a batch of feature rows gives a row each)."""
        return 1.0 / (1.0 + np.exp(-np.clip(self.logits(features), -60.0, 60.0)))

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The model as named arrays (a policy file's members)."""
        out = {f"{prefix}_mean": self.mean, f"{prefix}_std": self.std}
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            out[f"{prefix}_layer{index}_weight"] = weight
            out[f"{prefix}_layer{index}_bias"] = bias
        return out

    @classmethod
    def from_arrays(cls, arrays: dict, prefix: str, layers: int) -> "SuccessModel":
        if not (isinstance(layers, int) and not isinstance(layers, bool) and 1 <= layers <= MAX_LAYERS):
            raise ValueError(f"{prefix}: layers must be 1..{MAX_LAYERS}, got {layers!r}")
        return cls(arrays[f"{prefix}_mean"], arrays[f"{prefix}_std"],
                   [arrays[f"{prefix}_layer{i}_weight"] for i in range(layers)],
                   [arrays[f"{prefix}_layer{i}_bias"] for i in range(layers)])

    @classmethod
    def fit(cls, features, labels, mask=None, hidden: Sequence[int] = (64, 64), epochs: int = 300,
            learning_rate: float = 3e-3, weight_decay: float = 1e-3, batch_size: int = 64,
            holdout: float = 0.2, patience: int = 30, seed: int = 0) -> "SuccessModel":
        """Fit on `features` (n, d) and `labels` (n, k) in {0, 1}; `mask` (n, k) 1 where a label exists.

        AdamW on the masked binary cross-entropy; `holdout` of the rows (drawn with `seed`) stop the
        training when their loss has not improved for `patience` epochs, and the best epoch's weights
        are kept. Deterministic for a seed on one CPU."""
        import torch

        x = np.asarray(features, dtype=np.float64)
        y = np.asarray(labels, dtype=np.float64)
        m = np.ones_like(y) if mask is None else np.asarray(mask, dtype=np.float64)
        if x.ndim != 2 or y.ndim != 2 or len(y) != len(x) or m.shape != y.shape or len(x) < 2:
            raise ValueError(f"fit needs features (n, d), labels and mask (n, k) with n >= 2; got {x.shape}, "
                             f"{y.shape}, {m.shape}")
        generator = np.random.default_rng(seed)
        torch.manual_seed(seed)
        mean, std = x.mean(0), x.std(0) + 1e-6
        order = generator.permutation(len(x))
        n_hold = int(holdout * len(x)) if len(x) >= 10 else 0
        held, train = order[:n_hold], order[n_hold:]
        sizes = [x.shape[1], *hidden, y.shape[1]]
        layers: list = []
        for index in range(len(sizes) - 1):
            layers.append(torch.nn.Linear(sizes[index], sizes[index + 1]))
            if index < len(sizes) - 2:
                layers.append(torch.nn.Tanh())
        net = torch.nn.Sequential(*layers).double()
        optimiser = torch.optim.AdamW(net.parameters(), lr=learning_rate, weight_decay=weight_decay)
        xt, yt, mt = (torch.tensor(a) for a in ((x - mean) / std, y, m))

        def loss(rows):
            terms = torch.nn.functional.binary_cross_entropy_with_logits(net(xt[rows]), yt[rows], reduction="none")
            return (terms * mt[rows]).sum() / mt[rows].sum().clamp(min=1.0)

        best, best_state, waited = np.inf, None, 0
        for _ in range(epochs):
            net.train()
            shuffled = torch.tensor(generator.permutation(train))
            for start in range(0, len(shuffled), batch_size):
                optimiser.zero_grad()
                loss(shuffled[start:start + batch_size]).backward()
                optimiser.step()
            if n_hold:
                net.eval()
                with torch.no_grad():
                    held_loss = loss(torch.tensor(held)).item()
                if held_loss < best - 1e-4:
                    best, waited = held_loss, 0
                    best_state = [p.detach().clone() for p in net.parameters()]
                else:
                    waited += 1
                    if waited > patience:
                        break
        if best_state is not None:
            with torch.no_grad():
                for parameter, kept in zip(net.parameters(), best_state):
                    parameter.copy_(kept)
        linears = [layer for layer in net if isinstance(layer, torch.nn.Linear)]
        return cls(mean, std, [layer.weight.detach().numpy().T.copy() for layer in linears],
                   [layer.bias.detach().numpy().copy() for layer in linears])
