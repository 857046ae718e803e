"""The proxy networks (PyTorch): residual MLPs of width N, after the paper's Fig. 3."""

from __future__ import annotations

import torch
from torch import nn


class ResidualBlock(nn.Module):
    """Linear-ReLU-Linear with an identity skip, then ReLU."""

    def __init__(self, width: int):
        super().__init__()
        self.fc1 = nn.Linear(width, width)
        self.fc2 = nn.Linear(width, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(x + self.fc2(torch.relu(self.fc1(x))))


class ResidualMLP(nn.Module):
    """Input layer -> `blocks` residual blocks -> one output.

    x : (n, n_in) float32 encoded queries; returns (n,) float32, through a sigmoid when
    `sigmoid` (visibility) or raw (depth, t / box diagonal).
    """

    def __init__(self, n_in: int, width: int, blocks: int, sigmoid: bool):
        super().__init__()
        self.inp = nn.Linear(n_in, width)
        self.blocks = nn.Sequential(*[ResidualBlock(width) for _ in range(blocks)])
        self.out = nn.Linear(width, 1)
        self.sigmoid = sigmoid

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.out(self.blocks(torch.relu(self.inp(x)))).squeeze(-1)
        return torch.sigmoid(y) if self.sigmoid else y
