"""Networks for the learners.

* :class:`StackedLinear` / :class:`StackedMLP`: N independent per-agent layers whose weights are
  stacked into one ``(N, in, out)`` tensor, so that all N actors (or all N critics) of MADDPG run
  in one batched matmul (``torch.baddbmm``) instead of a Python loop over agents. Because Adam
  and per-agent gradient clipping act elementwise / per slice, training the stack is the same
  computation as training N separate networks (``tests/learners/test_networks.py`` checks this
  against :class:`LoopedMLP`, the textbook list of ``nn.Sequential``).
* :class:`BiRNNNet`: BiCNet's shared per-agent input layers, a bidirectional GRU run over the
  agent axis, and shared per-agent output layers.
* :class:`Workspace`, :func:`stacked_forward_` and :func:`stacked_backward_`: a stack of
  layers run forward into reused scratch tensors and differentiated by hand (MADDPG's update;
  see :meth:`learners.maddpg.MADDPG.update` for why).
* :class:`TorchOps` and :func:`select_torch_ops`: the few kernels for which a private torch op
  is faster than the public API (fused add + ReLU, in-place ReLU backward, multi-tensor lerp)
  and whether Adam can be fused on the CPU, chosen once, on first use. Every private op has a
  public fallback that computes the same numbers; it is used when the op is missing, raises or
  disagrees with the fallback on a probe, or when ``AGV_PRIVATE_TORCH_OPS=0`` is set.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

__all__ = [
    "StackedLinear", "StackedMLP", "LoopedMLP", "BiRNNNet", "Workspace", "TorchOps",
    "add_relu_", "clip_grad_norm_per_agent_", "grad_buffer", "linear_out_", "relu_backward_",
    "select_torch_ops", "stacked_backward_", "stacked_forward_", "torch_ops",
]


@dataclass(frozen=True)
class TorchOps:
    """The kernels the learners use, chosen once for this torch build by
    :func:`select_torch_ops`.

    Attributes
    ----------
    add_relu_ : callable
        ``(z, bias) -> z``, ``z <- relu(z + bias)`` in place (CPU tensors).
    relu_backward_ : callable
        ``(grad, act) -> grad``, ``grad <- 0`` where ``act <= 0``, in place.
    lerp_ : callable
        ``(targets, sources, weight) -> None``, ``t <- t + weight (s - t)`` for every pair.
    adam_fused : bool
        Whether ``torch.optim.Adam(fused=True)`` works on the CPU (torch >= 2.4); otherwise the
        optimizers use ``foreach=True``.
    private : tuple of str
        Names of the private torch ops in use (empty when every fallback is used).
    """

    add_relu_: Callable[[Tensor, Tensor], Tensor]
    relu_backward_: Callable[[Tensor, Tensor], Tensor]
    lerp_: Callable[[list[Tensor], list[Tensor], float], None]
    adam_fused: bool
    private: tuple[str, ...]


def _add_relu_public(z: Tensor, bias: Tensor) -> Tensor:
    return z.add_(bias).relu_()


def _add_relu_private(z: Tensor, bias: Tensor) -> Tensor:
    return torch.ops.aten._add_relu_(z, bias)


def _relu_backward_public(grad: Tensor, act: Tensor) -> Tensor:
    return grad.masked_fill_(act <= 0, 0.0)


def _relu_backward_private(grad: Tensor, act: Tensor) -> Tensor:
    return torch.ops.aten.threshold_backward.grad_input(grad, act, 0.0, grad_input=grad)


def _lerp_public(targets: list[Tensor], sources: list[Tensor], weight: float) -> None:
    for t, s in zip(targets, sources, strict=True):
        t.lerp_(s, weight)


def _lerp_private(targets: list[Tensor], sources: list[Tensor], weight: float) -> None:
    torch._foreach_lerp_(targets, sources, weight)


def _agrees(private: Callable[..., object], public: Callable[..., object],
            make_args: Callable[[], tuple]) -> bool:
    """Whether ``private`` runs and writes what ``public`` writes on a small probe."""
    want, got = make_args(), make_args()
    public(*want)
    try:
        private(*got)
    except (AttributeError, RuntimeError, TypeError, NotImplementedError):
        return False
    return all(torch.equal(a, b) for a, b in zip(_flat(want), _flat(got), strict=True))


def _flat(args: tuple) -> list[Tensor]:
    out: list[Tensor] = []
    for a in args:
        if isinstance(a, Tensor):
            out.append(a)
        elif isinstance(a, list):
            out.extend(a)
    return out


def _probe_args() -> dict[str, Callable[[], tuple]]:
    gen = torch.Generator().manual_seed(0)
    z = torch.randn(2, 5, 7, generator=gen)
    bias = torch.randn(2, 1, 7, generator=gen)
    a, b = [torch.randn(3, 4, generator=gen) for _ in range(2)], [torch.randn(6, generator=gen)]
    return {
        "add_relu_": lambda: (z.clone(), bias),
        "relu_backward_": lambda: (z.clone(), bias.expand_as(z).contiguous()),
        "lerp_": lambda: ([t.clone() for t in a] + [b[0].clone()], [t + 1 for t in a] + b, 0.25),
    }


def _fused_adam_works() -> bool:
    """Whether Adam(fused=True) runs on CPU tensors (torch >= 2.4)."""
    p = torch.zeros(3, requires_grad=True)
    p.grad = torch.ones(3)
    try:
        torch.optim.Adam([p], lr=0.1, fused=True).step()
    except (RuntimeError, ValueError, TypeError):
        return False
    return True


def select_torch_ops(private_ops: bool = True, fused_adam: bool = True) -> TorchOps:
    """Choose the learners' kernels (once; called on first use) and make them current.

    Parameters
    ----------
    private_ops : bool
        Allow the private torch ops ``aten._add_relu_``, ``aten.threshold_backward.grad_input``
        and ``torch._foreach_lerp_``; each is used only if it exists and matches its public
        fallback on a probe. With False every public fallback is used.
    fused_adam : bool
        Allow ``Adam(fused=True)`` where this torch supports it on the CPU (``foreach=True``
        otherwise). Affects optimizers created afterwards.

    Returns
    -------
    TorchOps
        The selection now used by :func:`add_relu_`, :func:`relu_backward_`,
        :func:`learners.common.soft_update_` and the learners' optimizers.
    """
    global _OPS
    candidates = {
        "add_relu_": (_add_relu_private, _add_relu_public, "aten._add_relu_"),
        "relu_backward_": (_relu_backward_private, _relu_backward_public,
                           "aten.threshold_backward.grad_input"),
        "lerp_": (_lerp_private, _lerp_public, "torch._foreach_lerp_"),
    }
    probes = _probe_args()
    chosen: dict[str, Callable] = {}
    used: list[str] = []
    for key, (private, public, name) in candidates.items():
        use_private = private_ops and _agrees(private, public, probes[key])
        chosen[key] = private if use_private else public
        if use_private:
            used.append(name)
    _OPS = TorchOps(adam_fused=fused_adam and _fused_adam_works(), private=tuple(used),
                    **chosen)
    return _OPS


def torch_ops() -> TorchOps:
    """The current :class:`TorchOps` selection, made on first use.

    Not at import: the fused-Adam probe runs an optimizer step, which imports
    ``torch._dynamo`` (about 2 s), and commands that train nothing should not pay for it.
    """
    if _OPS is None:
        return select_torch_ops(private_ops=os.environ.get("AGV_PRIVATE_TORCH_OPS", "1") != "0")
    return _OPS


_OPS: TorchOps | None = None


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
        """(B, N, in) -> (B, N, out).

        Runs agent-major, (N, B, ...), from the first layer to the last: the GRU steps along
        the agent axis, and in this layout its input, its output and every layer's activations
        are contiguous, so each fully connected layer is one matrix product over all B N rows.
        (Batch-major, the GRU's output is a transposed view, and a linear layer on it with
        autograd falls back to B small batched products plus a copy, about 5% of a BiCNet
        update.) The same computation as the batch-major textbook form (tested to 1e-6, values
        and gradients); the result is a (B, N, out) view of the (N, B, out) output.
        """
        h = torch.relu(self.encoder(x.transpose(0, 1).contiguous()))  # (N, B, H)
        # the GRU is batch_first: a (B, N, H) view of the agent-major tensor, read in place
        h, _ = self.rnn(h.transpose(0, 1))
        return self.decoder(h.transpose(0, 1)).transpose(0, 1)


def clip_grad_norm_per_agent_(params: Sequence[Tensor], max_norm: float) -> Tensor:
    """Clip the gradient of each agent's slice of stacked parameters to ``max_norm``.

    The same as calling ``torch.nn.utils.clip_grad_norm_`` on each of N separate networks:
    agent n's gradients are scaled by ``min(1, max_norm / (norm_n + 1e-6))``, where norm_n is
    the 2-norm of all of agent n's gradients together. Vectorised over the agents (one norm
    per parameter tensor, no loop over agents, no host synchronisation).

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
    per_tensor = torch.stack([torch.linalg.vector_norm(g.reshape(g.shape[0], -1), dim=1)
                              for g in grads])  # (P, N)
    norms = torch.linalg.vector_norm(per_tensor, dim=0)
    scale = (max_norm / (norms + 1e-6)).clamp_(max=1.0)
    for g in grads:
        g.mul_(scale.view(-1, *([1] * (g.dim() - 1))))
    return norms


class Workspace:
    """Scratch tensors kept from one call to the next, by name.

    Large temporaries that are allocated and freed on every update cost more than the
    arithmetic on them on CPU (fresh pages are zero-filled by the kernel on first touch);
    reusing them through ``out=`` arguments avoids that. A tensor is reallocated when the
    requested shape, dtype or device changes. Not part of any ``state_dict``.
    """

    def __init__(self) -> None:
        self._tensors: dict[str, Tensor] = {}

    def get(self, name: str, shape: Sequence[int], like: Tensor) -> Tensor:
        """An uninitialised tensor called ``name`` of ``shape``, with ``like``'s dtype and
        device (the same storage as the last call with that name and shape)."""
        shape = tuple(shape)
        t = self._tensors.get(name)
        if t is None or t.shape != shape or t.dtype != like.dtype or t.device != like.device:
            t = self._tensors[name] = torch.empty(shape, dtype=like.dtype, device=like.device)
        return t


def grad_buffer(param: Tensor) -> Tensor:
    """``param.grad``, allocated (uninitialised) if missing: a gradient written with ``out=``."""
    if param.grad is None or param.grad.shape != param.shape:
        param.grad = torch.empty_like(param)
    return param.grad


def stacked_forward_(
    layers: Sequence[StackedLinear], x: Tensor, ws: Workspace, tag: str,
    out: Tensor | None = None,
) -> list[Tensor]:
    """Forward pass of stacked layers (ReLU between them) into workspace tensors.

    Parameters
    ----------
    layers : sequence of StackedLinear
    x : Tensor, shape (N, B, in)
        Input (any strides).
    ws : Workspace
    tag : str
        Prefix of the workspace names (callers keep different passes apart).
    out : Tensor, optional
        Where to write the last layer's output (N, B, out), any strides (e.g. a transposed
        view of a (B, N, out) tensor); a workspace tensor otherwise.

    Returns
    -------
    list of Tensor
        ``[x, h_1, ..., h_{L-1}, out]``: entry k is the input of layer k (post-ReLU), the last
        one the output of the last layer (no activation). Entries after ``x`` live in ``ws``.
    """
    acts = [x]
    for k, layer in enumerate(layers):
        n, _, d_out = layer.weight.shape
        last = k == len(layers) - 1
        z = out if last and out is not None else ws.get(f"{tag}{k}", (n, x.shape[1], d_out), x)
        if not last:
            torch.bmm(acts[-1], layer.weight, out=z)
            add_relu_(z, layer.bias)
        else:
            linear_out_(acts[-1], layer, z)
        acts.append(z)
    return acts


def add_relu_(z: Tensor, bias: Tensor) -> Tensor:
    """``z <- relu(z + bias)`` in place (bias broadcast); one pass over ``z`` on CPU where the
    private fused op is available (see :func:`select_torch_ops`).

    Parameters
    ----------
    z : Tensor, shape (N, B, H)
    bias : Tensor, broadcastable to ``z``, e.g. (N, 1, H)

    Returns
    -------
    Tensor
        ``z``.
    """
    if z.device.type == "cpu":
        return torch_ops().add_relu_(z, bias)
    return _add_relu_public(z, bias)


def relu_backward_(grad: Tensor, act: Tensor) -> Tensor:
    """ReLU backward in place: ``grad <- 0`` where the activation ``act`` is not positive.

    Parameters
    ----------
    grad : Tensor
        Gradient with respect to the ReLU's output, overwritten with the gradient with respect
        to its input.
    act : Tensor, the shape of ``grad``
        The ReLU's output (or input: the sign is the same).

    Returns
    -------
    Tensor
        ``grad``.
    """
    return torch_ops().relu_backward_(grad, act)


def linear_out_(x: Tensor, layer: StackedLinear, out: Tensor) -> Tensor:
    """A stacked layer without activation, ``out <- x W + b``, (N, B, in) -> (N, B, out).

    With one output (a critic's last layer) the N products are matrix-vector products, which
    ``torch.mv`` does faster than a batched matmul with one column.
    """
    if layer.out_features == 1:
        for i in range(layer.num_stacks):
            torch.mv(x[i], layer.weight[i, :, 0], out=out[i, :, 0])
        return out.add_(layer.bias)
    return torch.baddbmm(layer.bias, x, layer.weight, out=out)


def stacked_backward_(
    layers: Sequence[StackedLinear], acts: Sequence[Tensor], grad_out: Tensor, ws: Workspace,
    tag: str, stop: int = 0, param_grads: bool = True, grad_in_out: Tensor | None = None,
) -> Tensor | None:
    """Backward pass of :func:`stacked_forward_`, by hand, gradients written in place.

    Parameters
    ----------
    layers : sequence of StackedLinear
    acts : sequence of Tensor
        Inputs of the layers as returned by :func:`stacked_forward_` (``acts[k]`` feeds layer
        k; post-ReLU for k >= 1, which also gives the ReLU mask).
    grad_out : Tensor, shape (N, B, out)
        Gradient of the loss with respect to the last layer's output.
    ws : Workspace
    tag : str
        Prefix of the workspace names.
    stop : int
        Differentiate layers ``stop, ..., L - 1`` only; the gradient with respect to the
        pre-activation of layer ``stop`` (``stop >= 1``) is returned.
    param_grads : bool
        Write the weight and bias gradients of those layers to their ``.grad`` (overwritten,
        not accumulated); with False only the input gradient is computed.
    grad_in_out : Tensor, optional
        Where to write the returned gradient (any strides); a workspace tensor otherwise.

    Returns
    -------
    Tensor or None
        With ``stop >= 1``, d loss / d (pre-activation output of layer ``stop - 1``), i.e.
        the gradient at the input of layer ``stop`` passed back through its ReLU; None for
        ``stop == 0``.
    """
    dz = grad_out
    for k in range(len(layers) - 1, stop - 1, -1):
        layer = layers[k]
        single = layer.out_features == 1
        if param_grads:
            gw = grad_buffer(layer.weight)
            if single:
                for i in range(layer.num_stacks):
                    torch.mv(acts[k][i].t(), dz[i, :, 0], out=gw[i, :, 0])
            else:
                torch.bmm(acts[k].transpose(1, 2), dz, out=gw)
            torch.sum(dz, dim=1, keepdim=True, out=grad_buffer(layer.bias))
        if k == 0:
            return None
        out = (grad_in_out if k == stop and grad_in_out is not None
               else ws.get(f"{tag}{k}", acts[k].shape, dz))
        if single:
            torch.mul(dz, layer.weight.transpose(1, 2), out=out)
        else:
            torch.bmm(dz, layer.weight.transpose(1, 2), out=out)
        relu_backward_(out, acts[k])
        dz = out
    return dz
