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


class Fourier(nn.Module):
    """x -> [x, sin(2^k pi x), cos(2^k pi x) for k < octaves]: sharp boundaries in few steps."""

    def __init__(self, octaves: int):
        super().__init__()
        self.octaves = octaves
        self.register_buffer("freq", (2.0 ** torch.arange(octaves)) * torch.pi)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.octaves == 0:
            return x
        xf = (x.unsqueeze(-1) * self.freq).flatten(1)  # (n, n_in * octaves)
        return torch.cat([x, torch.sin(xf), torch.cos(xf)], dim=1)


class ResidualMLP(nn.Module):
    """Input layer -> `blocks` residual blocks -> one output.

    x : (n, n_in) float32 encoded queries; returns (n,) float32, through a sigmoid when
    `sigmoid` (visibility) or raw (depth target, see nprt.proxies.encoding.depth_target).
    """

    def __init__(self, n_in: int, width: int, blocks: int, sigmoid: bool, fourier: int = 0):
        super().__init__()
        self.features = Fourier(fourier)
        self.inp = nn.Linear(n_in * (1 + 2 * fourier), width)
        self.blocks = nn.Sequential(*[ResidualBlock(width) for _ in range(blocks)])
        self.out = nn.Linear(width, 1)
        self.sigmoid = sigmoid

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.out(self.blocks(torch.relu(self.inp(self.features(x))))).squeeze(-1)
        return torch.sigmoid(y) if self.sigmoid else y
