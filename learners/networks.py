"""Networks for the learners.

* :class:`StackedLinear` / :class:`StackedMLP`: N independent per-agent layers whose weights are
  stacked into one ``(N, in, out)`` tensor, so that all N actors (or all N critics) of MADDPG run
  in one batched matmul (``torch.baddbmm``) instead of a Python loop over agents. Because Adam
  and per-agent gradient clipping act elementwise / per slice, training the stack is the same
  computation as training N separate networks (``tests/learners/test_networks.py`` checks this
  against :class:`LoopedMLP`, the textbook list of ``nn.Sequential``).
* :class:`BiRNNNet`: BiCNet's shared per-agent input layers, a bidirectional GRU run over the
  agent axis, and shared per-agent output layers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

__all__ = [
    "StackedLinear", "StackedMLP", "LoopedMLP", "BiRNNNet", "clip_grad_norm_per_agent_",
]


class StackedLinear(nn.Module):
    """N independent affine maps ``y_n = x_n W_n + b_n`` in one ``torch.baddbmm``.

    Parameters
    ----------
    num_stacks : int
        Number N of independent layers (one per agent).
    in_features, out_features : int
    init_scale : float, optional
        If given, weights and biases are drawn from U(-init_scale, init_scale) instead of the
        ``nn.Linear`` default U(-1/sqrt(in), 1/sqrt(in)) (DDPG's small last-layer init).

    Attributes
    ----------
    weight : Parameter, shape (N, in_features, out_features)
    bias : Parameter, shape (N, 1, out_features)
    """

    def __init__(
        self, num_stacks: int, in_features: int, out_features: int,
        init_scale: float | None = None,
    ) -> None:
        super().__init__()
        self.num_stacks, self.in_features, self.out_features = num_stacks, in_features, out_features
        self.weight = nn.Parameter(torch.empty(num_stacks, in_features, out_features))
        self.bias = nn.Parameter(torch.empty(num_stacks, 1, out_features))
        bound = 1.0 / math.sqrt(in_features) if init_scale is None else init_scale
        with torch.no_grad():
            self.weight.uniform_(-bound, bound)
            self.bias.uniform_(-bound, bound)

    def forward(self, x: Tensor, index: Tensor | None = None) -> Tensor:
        """(N, B, in) -> (N, B, out); with ``index`` (K,), layer ``index[k]`` maps ``x[k]``."""
        if index is None:
            return torch.baddbmm(self.bias, x, self.weight)
        return torch.baddbmm(self.bias[index], x, self.weight[index])

    def extra_repr(self) -> str:
        return f"num_stacks={self.num_stacks}, in={self.in_features}, out={self.out_features}"


def _hidden_sizes(hidden: int | Sequence[int], layers: int) -> list[int]:
    if isinstance(hidden, int):
        return [hidden] * (layers - 1)
    return list(hidden)


class StackedMLP(nn.Module):
    """N independent MLPs (ReLU between layers) evaluated together.

    Parameters
    ----------
    num_stacks : int
        Number N of MLPs (one per agent).
    in_features, out_features : int
    hidden : int or sequence of int
        Width of the hidden layers (an int repeats ``layers - 1`` times).
    layers : int
        Number of fully connected layers (3 in the paper's MADDPG).
    out_init_scale : float, optional
        Uniform init range of the last layer (see :class:`StackedLinear`).
    """

    def __init__(
        self, num_stacks: int, in_features: int, out_features: int,
        hidden: int | Sequence[int] = 64, layers: int = 3, out_init_scale: float | None = None,
    ) -> None:
        super().__init__()
        sizes = [in_features, *_hidden_sizes(hidden, layers), out_features]
        self.layers = nn.ModuleList(
            StackedLinear(num_stacks, a, b, init_scale=out_init_scale if i == len(sizes) - 2
                          else None)
            for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True))
        )

    def forward(self, x: Tensor, index: Tensor | None = None) -> Tensor:
        """(N, B, in) -> (N, B, out); an (B, in) input is shared by all N MLPs.

        With ``index`` (K,) of MLP numbers, ``x`` is (K, B, in) and MLP ``index[k]`` maps
        ``x[k]`` (one MLP may serve several rows).
        """
        if x.dim() == 2:
            x = x.unsqueeze(0).expand(self.layers[0].num_stacks, -1, -1)
        for i, layer in enumerate(self.layers):
            x = layer(x, index)
            if i < len(self.layers) - 1:
                x = torch.relu(x)
        return x


class LoopedMLP(nn.Module):
    """The textbook layout: a list of N separate ``nn.Sequential`` MLPs run in a Python loop.

    Used by the speed benchmark and by the tests that check :class:`StackedMLP` computes the
    same thing. :meth:`from_stacked` copies a stack's weights into separate networks.
    """

    def __init__(
        self, num_stacks: int, in_features: int, out_features: int,
        hidden: int | Sequence[int] = 64, layers: int = 3,
    ) -> None:
        super().__init__()
        sizes = [in_features, *_hidden_sizes(hidden, layers), out_features]
        nets = []
        for _ in range(num_stacks):
            mods: list[nn.Module] = []
            for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
                mods.append(nn.Linear(a, b))
                if i < len(sizes) - 2:
                    mods.append(nn.ReLU())
            nets.append(nn.Sequential(*mods))
        self.nets = nn.ModuleList(nets)

    @classmethod
    def from_stacked(cls, stacked: StackedMLP) -> LoopedMLP:
        """Separate networks holding copies of a stack's weights."""
        first = stacked.layers[0]
        sizes = [lay.out_features for lay in stacked.layers]
        out = cls(first.num_stacks, first.in_features, sizes[-1], sizes[:-1], len(sizes))
        with torch.no_grad():
            for n, net in enumerate(out.nets):
                linears = [m for m in net if isinstance(m, nn.Linear)]
                for lin, lay in zip(linears, stacked.layers, strict=True):
                    lin.weight.copy_(lay.weight[n].T)
                    lin.bias.copy_(lay.bias[n, 0])
        return out

    def forward(self, x: Tensor) -> Tensor:
        """(N, B, in) -> (N, B, out), one network at a time; (B, in) is shared by all."""
        if x.dim() == 2:
            return torch.stack([net(x) for net in self.nets])
        return torch.stack([net(x[n]) for n, net in enumerate(self.nets)])


def _mlp(sizes: Sequence[int], out_init_scale: float | None = None) -> nn.Sequential:
    mods: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        lin = nn.Linear(a, b)
        if out_init_scale is not None and i == len(sizes) - 2:
            nn.init.uniform_(lin.weight, -out_init_scale, out_init_scale)
            nn.init.uniform_(lin.bias, -out_init_scale, out_init_scale)
        mods.append(lin)
        if i < len(sizes) - 2:
            mods.append(nn.ReLU())
    return nn.Sequential(*mods)


class BiRNNNet(nn.Module):
    """BiCNet's network: shared per-agent input layers, a bidirectional GRU over the agents,
    shared per-agent output layers.

    The recurrence runs along the agent axis (agent 0, 1, ..., N-1 forwards and back), so every
    agent's output depends on every agent's input: BiCNet's implicit communication. All weights
    are shared by the agents, so one network serves any N.

    Parameters
    ----------
    in_features : int
        Per-agent input size (the observation, plus the action for a critic).
    out_features : int
        Per-agent output size (2 for an actor, 1 for a critic).
    hidden : int
        Width of the fully connected layers and of each GRU direction.
    input_layers, output_layers : int
        Fully connected layers before and after the GRU (the output count includes the last,
        linear layer).
    out_init_scale : float, optional
        Uniform init range of the last layer.
    """

    def __init__(
        self, in_features: int, out_features: int, hidden: int = 64, input_layers: int = 2,
        output_layers: int = 2, out_init_scale: float | None = None,
    ) -> None:
        super().__init__()
        if input_layers < 1 or output_layers < 1:
            raise ValueError("BiRNNNet needs at least one input and one output layer")
        self.encoder = _mlp([in_features] + [hidden] * input_layers)
        self.rnn = nn.GRU(hidden, hidden, batch_first=True, bidirectional=True)
        self.decoder = _mlp([2 * hidden] + [hidden] * (output_layers - 1) + [out_features],
                            out_init_scale)

    def forward(self, x: Tensor) -> Tensor:
        """(B, N, in) -> (B, N, out)."""
        h = torch.relu(self.encoder(x))
        h, _ = self.rnn(h)
        return self.decoder(h)


def clip_grad_norm_per_agent_(params: Sequence[Tensor], max_norm: float) -> Tensor:
    """Clip the gradient of each agent's slice of stacked parameters to ``max_norm``.

    The same as calling ``torch.nn.utils.clip_grad_norm_`` on each of N separate networks.

    Parameters
    ----------
    params : sequence of Tensor
        Stacked parameters, each with the agent axis first, shape (N, ...), with ``.grad`` set.
    max_norm : float

    Returns
    -------
    Tensor, shape (N,)
        The per-agent gradient norms before clipping.
    """
    grads = [p.grad for p in params if p.grad is not None]
    sq = torch.stack([g.reshape(g.shape[0], -1).pow(2).sum(1) for g in grads]).sum(0)
    norms = sq.sqrt()
    scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(scale.view(-1, *([1] * (g.dim() - 1))))
    return norms
