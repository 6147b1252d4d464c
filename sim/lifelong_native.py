"""The lifelong step's observations, pair distances, collisions and remaining work in C.

Thin wrappers over the kernels of ``sim/_native/lifelong.h`` (built and loaded by
:mod:`sim.native`): each checks its tensors with :func:`sim.native.pointer` (dtype, shape,
CPU, contiguity), allocates the outputs and loops over the floors in C. The torch functions
stay the definitions and the tests hold the kernels to them:

- :func:`lifelong_observe`: :func:`sim.observations.observe_lifelong` and
  :func:`sim.physics.pair_distances` (the same floats);
- :func:`lifelong_observe_collisions`: the same, and :func:`sim.physics.collisions` from the
  pair distances in the same pass;
- :func:`remaining_work`: :func:`sim.tasks.remaining_work` (each order's term the same
  float32 value; the sum in double, rounded once, so within float32 rounding of torch's sum).

The AGV-pickup distances that choose the nearest pickups, like the lengths of
:func:`sim.tasks.remaining_work`, are ``torch.linalg.vector_norm``'s and ``torch.cdist``'s,
whose last bit depends on the CPU kernel torch runs (with or without fused multiply-add);
:func:`torch_norm_rounding` asks torch once and the kernels round the same way.
"""

from __future__ import annotations

import functools
import math
from numbers import Real

import numpy as np
import torch
from torch import Tensor

from sim import native

__all__ = ["lifelong_observe", "lifelong_observe_collisions", "lifelong_pickups", "obs_size",
           "remaining_work",
           "torch_norm_rounding"]

_F32, _I64, _I8, _BOOL = torch.float32, torch.int64, torch.int8, torch.bool


def obs_size(k_pickups: int, k_agents: int) -> int:
    """Length O of a lifelong observation (``LifelongObsLayout(k_pickups, k_agents).size``)."""
    return 12 + 3 * k_pickups + 5 * k_agents


@functools.cache
def torch_norm_rounding() -> tuple[bool, bool]:
    """Whether ``torch.linalg.vector_norm`` and ``torch.cdist`` (``donot_use_mm``) round the
    length of a float32 2-vector ``(x, y)`` as ``sqrt(fma(y, y, x * x))`` (True) or as
    ``sqrt(x * x + y * y)`` (False) in this process.

    Found once by asking torch for the lengths of 4096 fixed vectors whose two roundings
    differ in some last bits, against both predictions computed exactly in numpy.

    Returns
    -------
    (vector_norm_fused, cdist_fused) : tuple of bool

    Raises
    ------
    RuntimeError
        When torch rounds neither way (the kernels cannot match it; use the torch path).
    """
    rng = np.random.default_rng(0)
    xy = rng.uniform(1.0, 2.0, size=(4096, 2)).astype(np.float32)
    x, y = xy[:, 0], xy[:, 1]
    plain = np.sqrt(x * x + y * y)  # float32 products, sum and a correctly rounded sqrt
    # fma(y, y, x * x): x * x in float32, y * y and the sum exact in float64 (x, y in [1, 2):
    # at most 49 significant bits), then one rounding to float32.
    fused = np.sqrt((np.float64(1.0) * (x * x) + y.astype(np.float64) ** 2).astype(np.float32))
    assert not np.array_equal(plain, fused)
    t = torch.from_numpy(xy)
    norm = torch.linalg.vector_norm(t, dim=-1).numpy()
    cdist = torch.cdist(t.view(1, -1, 2), torch.zeros(1, 3, 2),
                        compute_mode="donot_use_mm_for_euclid_dist")[0, :, 0].numpy()
    out = []
    for name, got in (("torch.linalg.vector_norm", norm), ("torch.cdist", cdist)):
        if np.array_equal(got, fused):
            out.append(True)
        elif np.array_equal(got, plain):
            out.append(False)
        else:
            raise RuntimeError(f"{name} rounds a 2-vector's length neither as "
                               "sqrt(fma(y, y, x * x)) nor as sqrt(x * x + y * y); the lifelong "
                               "kernels cannot match it")
    return out[0], out[1]


def _lib():  # noqa: ANN202
    lib = native.library()
    if lib is None:
        raise RuntimeError(f"sim.lifelong_native: the C kernels are unavailable "
                           f"({native.disabled_reason()}); use the torch path")
    return lib


def _sizes(tensor: object, dtype: torch.dtype, shape: tuple[int, ...], name: str
           ) -> tuple[int, ...]:
    """The sizes of a tensor with ``len(shape)`` dimensions (``native.pointer``'s message
    otherwise); the exact check comes with the call's :func:`sim.native.pointer`."""
    if not (type(tensor) is torch.Tensor and tensor.dim() == len(shape)):
        native.pointer(tensor, dtype, shape, name)  # raises, naming the argument
    assert isinstance(tensor, Tensor)
    return tuple(tensor.shape)


def _count(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
    return int(value)


def _real(value: object, name: str, *, finite: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, Real) or math.isnan(float(value)):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    if finite and not math.isfinite(float(value)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if float(value) < 0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return float(value)


def _observe(agent_pos: Tensor, agent_vel: Tensor, status: Tensor, service_left: Tensor,
             target: Tensor, has_target: Tensor, pickup: Tensor, order_status: Tensor,
             k_pickups: int, k_agents: int, sensing_range: float,
             active: Tensor | None, agent_radius: float | None
             ) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
    lib = _lib()
    B, N, _ = _sizes(agent_pos, _F32, (-1, -1, 2), "agent_pos")
    Q = _sizes(pickup, _F32, (B, -1, 2), "pickup")[1]
    kp = _count(k_pickups, "k_pickups")
    ka = _count(k_agents, "k_agents")
    rng = _real(sensing_range, "sensing_range", finite=False)
    fused, _ = torch_norm_rounding()
    args = [
        native.pointer(agent_pos, _F32, (B, N, 2), "agent_pos"),
        native.pointer(agent_vel, _F32, (B, N, 2), "agent_vel"),
        native.pointer(status, _I8, (B, N), "status"),
        native.pointer(service_left, _I64, (B, N), "service_left"),
        native.pointer(target, _F32, (B, N, 2), "target"),
        native.pointer(has_target, _BOOL, (B, N), "has_target"),
        native.pointer(pickup, _F32, (B, Q, 2), "pickup"),
        native.pointer(order_status, _I8, (B, Q), "order_status"),
    ]
    obs = torch.empty(B, N, obs_size(kp, ka), dtype=_F32)
    pair = torch.empty(B, N, N, dtype=_F32)
    per_agent = pairs = None
    collide = 0.0
    if active is not None:
        args.append(native.pointer(active, _BOOL, (B,), "active"))
        collide = 2.0 * _real(agent_radius, "agent_radius", finite=True)
        per_agent = torch.empty(B, N, dtype=_F32)
        pairs = torch.empty(B, dtype=_F32)
    else:
        args.append(None)
    rc = lib.agv_lifelong_observe(
        B, N, Q, kp, ka, rng, int(fused), collide, *args, obs.data_ptr(), pair.data_ptr(),
        None if per_agent is None else per_agent.data_ptr(),
        None if pairs is None else pairs.data_ptr())
    if rc == -1:
        raise MemoryError("agv_lifelong_observe: out of memory")
    if rc:
        bad = ((status < 0) | (status > 3)).nonzero()[0].tolist()
        raise ValueError(f"status must hold AGENT_STATUS codes 0..3, got "
                         f"{int(status[bad[0], bad[1]])} at (env {bad[0]}, AGV {bad[1]})")
    return obs, pair, per_agent, pairs


def lifelong_observe(agent_pos: Tensor, agent_vel: Tensor, status: Tensor, service_left: Tensor,
                     target: Tensor, has_target: Tensor, pickup: Tensor, order_status: Tensor,
                     k_pickups: int, k_agents: int, sensing_range: float
                     ) -> tuple[Tensor, Tensor]:
    """Lifelong observations and pair distances in C: exactly
    ``observe_lifelong(agent_pos, agent_vel, fleet, orders, target, has_target,
    LifelongObsLayout(k_pickups, k_agents), sensing_range, pair, eye)`` and
    ``pair = sim.physics.pair_distances(agent_pos)``.

    Parameters
    ----------
    agent_pos, agent_vel : Tensor, float32, shape (B, N, 2)
    status : Tensor, int8, shape (B, N)
        ``fleet.status`` (:data:`sim.orders.AGENT_STATUS` codes).
    service_left : Tensor, int64, shape (B, N)
        ``fleet.service_left``.
    target : Tensor, float32, shape (B, N, 2)
    has_target : Tensor, bool, shape (B, N)
        ``LifelongEnv.targets()``.
    pickup : Tensor, float32, shape (B, Q, 2)
    order_status : Tensor, int8, shape (B, Q)
        ``orders.pickup`` and ``orders.status``; the pickups shown are the OPEN orders'.
    k_pickups, k_agents : int
        Slots (>= 0).
    sensing_range : float
        Pickups and AGVs farther than this (compared in float32) are hidden; may be inf.

    Returns
    -------
    obs : Tensor, float32, shape (B, N, 12 + 3 k_pickups + 5 k_agents)
    pair : Tensor, float32, shape (B, N, N)

    Raises
    ------
    ValueError
        Naming the argument, for a tensor of another dtype or shape, off the CPU or not
        contiguous, bad slot counts or range, or a status code outside 0..3.
    RuntimeError
        Where the kernels are unavailable (see :func:`sim.native.library_for`) or torch's
        rounding cannot be matched (:func:`torch_norm_rounding`).

    Notes
    -----
    The positions must be finite (the env's state guarantees it); nothing checks it here.
    """
    obs, pair, _, _ = _observe(agent_pos, agent_vel, status, service_left, target, has_target,
                               pickup, order_status, k_pickups, k_agents, sensing_range,
                               None, None)
    return obs, pair


def lifelong_observe_collisions(
    agent_pos: Tensor, agent_vel: Tensor, status: Tensor, service_left: Tensor, target: Tensor,
    has_target: Tensor, pickup: Tensor, order_status: Tensor, k_pickups: int, k_agents: int,
    sensing_range: float, active: Tensor, agent_radius: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`lifelong_observe` and, in the same pass, exactly
    ``sim.physics.collisions(pair, active, agent_radius, eye, triu)``.

    Parameters
    ----------
    agent_pos, agent_vel, status, service_left, target, has_target, pickup, order_status,
    k_pickups, k_agents, sensing_range
        As :func:`lifelong_observe`.
    active : Tensor, bool, shape (B,)
        Floors that run (collisions count 0 elsewhere).
    agent_radius : float
        Two discs overlap below ``2 agent_radius`` (compared in float32).

    Returns
    -------
    obs : Tensor, float32, shape (B, N, O)
    pair : Tensor, float32, shape (B, N, N)
    per_agent : Tensor, float32, shape (B, N)
        Other discs each AGV overlaps.
    pairs : Tensor, float32, shape (B,)
        Overlapping pairs.

    Raises
    ------
    ValueError, RuntimeError
        As :func:`lifelong_observe`; also for ``active`` or ``agent_radius``.
    """
    if not isinstance(active, Tensor):
        raise ValueError(f"active must be a bool tensor of shape (B,), got "
                         f"{type(active).__name__}")
    obs, pair, per_agent, pairs = _observe(
        agent_pos, agent_vel, status, service_left, target, has_target, pickup, order_status,
        k_pickups, k_agents, sensing_range, active, agent_radius)
    assert per_agent is not None and pairs is not None
    return obs, pair, per_agent, pairs


def remaining_work(agent_pos: Tensor, order_status: Tensor, pickup: Tensor, dropoff: Tensor,
                   order_agent: Tensor, agent_status: Tensor, active: Tensor) -> Tensor:
    """The lifelong remaining work in C: :func:`sim.tasks.remaining_work` with ``orders``'
    ``status``, ``pickup``, ``dropoff`` and ``agent`` passed one by one.

    Each order's term is the float32 value torch computes; the terms are summed in double and
    rounded once (torch sums in float32 in an order of its own: the two agree within
    ``(Q + 1) 2**-24`` times the sum).

    Parameters
    ----------
    agent_pos : Tensor, float32, shape (B, N, 2)
    order_status : Tensor, int8, shape (B, Q)
    pickup, dropoff : Tensor, float32, shape (B, Q, 2)
    order_agent : Tensor, int64, shape (B, Q)
        ``orders.agent``: the carrying AGV of a LOADED order (-1 for none; < N).
    agent_status : Tensor, int8, shape (B, N)
        ``fleet.status``.
    active : Tensor, bool, shape (B,)

    Returns
    -------
    Tensor, float32, shape (B,); 0 where inactive.

    Raises
    ------
    ValueError
        Naming the argument, for a tensor of another dtype or shape, off the CPU or not
        contiguous, or an AGV index >= N in ``order_agent``.
    RuntimeError
        As :func:`lifelong_observe`.
    """
    lib = _lib()
    B, N, _ = _sizes(agent_pos, _F32, (-1, -1, 2), "agent_pos")
    Q = _sizes(order_status, _I8, (B, -1), "order_status")[1]
    if N == 0 and Q > 0:
        raise ValueError("agent_pos: remaining_work needs at least one AGV (N >= 1)")
    fused_norm, fused_cdist = torch_norm_rounding()
    out = torch.empty(B, dtype=_F32)
    rc = lib.agv_lifelong_remaining_work(
        B, N, Q, int(fused_cdist), int(fused_norm),
        native.pointer(agent_pos, _F32, (B, N, 2), "agent_pos"),
        native.pointer(order_status, _I8, (B, Q), "order_status"),
        native.pointer(pickup, _F32, (B, Q, 2), "pickup"),
        native.pointer(dropoff, _F32, (B, Q, 2), "dropoff"),
        native.pointer(order_agent, _I64, (B, Q), "order_agent"),
        native.pointer(agent_status, _I8, (B, N), "agent_status"),
        native.pointer(active, _BOOL, (B,), "active"),
        out.data_ptr())
    if rc:
        bad = (order_agent >= N).nonzero()[0].tolist()
        raise ValueError(f"order_agent must hold AGV indices < N = {N} (or -1), got "
                         f"{int(order_agent[bad[0], bad[1]])} at (env {bad[0]}, slot {bad[1]})")
    return out


def lifelong_pickups(agent_pos: Tensor, ready: Tensor, agent_order: Tensor, pickup: Tensor,
                     dropoff: Tensor, order_status: Tensor, key: Tensor, capture_radius: float
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """The step's pickups and drop-offs (``sim/_native/orders.h``): :func:`sim.orders.pickups`
    and :func:`sim.orders.dropoffs` in one pass.

    Parameters
    ----------
    agent_pos : Tensor, float32, shape (B, N, 2)
    ready : Tensor, bool, shape (B, N)
        AGVs that may pick up or drop off in this step.
    agent_order : Tensor, int64, shape (B, N)
        Each AGV's order slot, -1 for none (an AGV with one may pick up only that one).
    pickup, dropoff : Tensor, float32, shape (B, Q, 2)
    order_status : Tensor, int8, shape (B, Q)
    key : Tensor, int64, shape (B, Q)
        :func:`sim.orders.tie_key`.
    capture_radius : float

    Returns
    -------
    takes : Tensor of bool, shape (B, N)
    slot : Tensor of int64, shape (B, N)
        The slot each AGV that takes picks up (0 elsewhere).
    at_drop : Tensor of bool, shape (B, N)
        Ready AGVs with a loaded order whose drop-off they reach.
    """
    lib = _lib()
    B, N, _ = _sizes(agent_pos, _F32, (-1, -1, 2), "agent_pos")
    Q = _sizes(order_status, _I8, (B, -1), "order_status")[1]
    _sizes(agent_order, _I64, (B, N), "agent_order")
    if agent_order.numel() and int(agent_order.max()) >= Q:
        raise ValueError(f"agent_order must hold slots < Q = {Q} (or -1), got "
                         f"{int(agent_order.max())}")
    fused_norm, fused_cdist = torch_norm_rounding()
    takes = torch.empty(B, N, dtype=_BOOL)
    slot = torch.empty(B, N, dtype=_I64)
    at_drop = torch.empty(B, N, dtype=_BOOL)
    rc = lib.agv_lifelong_pickups(
        B, N, Q, _real(capture_radius, "capture_radius", finite=True), int(fused_cdist),
        int(fused_norm),
        native.pointer(agent_pos, _F32, (B, N, 2), "agent_pos"),
        native.pointer(ready, _BOOL, (B, N), "ready"),
        native.pointer(agent_order, _I64, (B, N), "agent_order"),
        native.pointer(pickup, _F32, (B, Q, 2), "pickup"),
        native.pointer(dropoff, _F32, (B, Q, 2), "dropoff"),
        native.pointer(order_status, _I8, (B, Q), "order_status"),
        native.pointer(key, _I64, (B, Q), "key"), takes.data_ptr(), slot.data_ptr(),
        at_drop.data_ptr())
    if rc:
        raise MemoryError("the pickup kernel could not allocate its scratch space")
    return takes, slot, at_drop
