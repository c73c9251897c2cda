"""Learning benchmark: jaximu's training step against the same network and loss in PyTorch.

    python benchmarks/learning.py --data DIR...         # steps + integration (~3-5 min)
    python benchmarks/learning.py --data DIR... --quick # fewer repeats (smoke test)
    python benchmarks/learning.py --data DIR... --full-training   # also a whole `train` run
    python benchmarks/learning.py --data DIR... --full-training --train-minutes 3  # cut at 3 min
    python benchmarks/learning.py --data DIR... --torch-compile   # also torch.compile's step

Workloads, all float32 on the sequence folders given by ``--data`` (the five EuRoC training
sequences), read with :func:`jaximu.learning.load_sequence`:

1. **Training step.** jaximu's own jitted step of :func:`jaximu.learning.train` (random
   offsets, input noise, the denoiser, :func:`~jaximu.learning.losses.increment_loss` with
   its NLL, gradient, AdamW update) on the batch ``train`` uses: every sequence's first 80 s,
   ``S × L`` samples (5 × 14,336 by default). The step function is taken from ``train``
   itself (its ``eqx.filter_jit`` is intercepted at the first call, see
   :func:`capture_train_step`), so what is timed is the library's step, not a copy. Also the same step with the loss's NLL
   term left out (``bias_sigma=None``: the Huber loss alone, what the PyTorch step computes).
   Compile time is reported apart.
2. **PyTorch.** The same network written as a PyTorch user writes it (channels-first
   ``Conv1d``, replication left-padding, tanh-GELU as ``jax.nn.gelu``, dropout, the gyro
   correction, the noise head), eager, ``torch.set_num_threads(2)``, the configured-horizon
   increment Huber loss with the first horizon's windows integrated by PyPose's
   ``pp.module.IMUPreintegrator`` (a plain PyTorch quaternion product when PyPose is not
   installed, or with ``--torch-integration plain``), and ``torch.optim.AdamW``; on the GPU
   when JAX runs on one (``--torch-device``), eager and, with ``--torch-compile``, with its
   forward and loss through ``torch.compile``; on batches
   of the same size with its own random offsets and noise. Before timing, a converter copies
   a JAX model's weights into the PyTorch model and the corrected gyro, the noise density,
   the loss and a gradient are compared on a small batch (float32).
3. **Integration alone.** ``jaximu.preintegrate`` of the step's windows (``S × W`` windows
   of 16 samples, as the loss cuts them), forward and ``jax.grad`` of a scalar of
   ``delta_q`` with respect to the gyro, against PyPose's ``IMUPreintegrator`` on the same
   windows batched as ``(S·W, 16, 3)`` (forward; forward + backward).

Timing: after warm-up, the variants of a workload run alternately (jaximu, PyTorch, jaximu
without NLL, jaximu, PyTorch, ...) for ``--repeats`` rounds; the figure is the median over
rounds, and ratios are also given as the median of each round's ratio (this host's speed
drifts within minutes; a ratio taken within one round cancels it). The share of the CPUs
that other processes used while timing is recorded: treat figures from a busy machine as
lower bounds.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import pathlib
import statistics
import sys
import time

import jax

# the shared helpers (machine description, CPU meter) live in propagation.py, which turns
# float64 on at import: the learning code is float32 throughout (its random noise included),
# so it is turned off again before anything is traced
from propagation import CpuMeter, machine_info, machine_slug

jax.config.update("jax_enable_x64", False)

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import jaximu
from jaximu.learning import TrainConfig, load_sequence, train
from jaximu.learning import training as training_module
from jaximu.learning.losses import increment_loss

HERE = pathlib.Path(__file__).resolve().parent
TORCH_THREADS = 2
INTEGRATION_TARGET = 3.0  # jaximu ≥ 3× PyPose on the loss's windows (forward + backward)
CHECK_RTOL = 1e-5  # float32 agreement of the JAX and PyTorch functions on the check batch


# --------------------------------------------------------------------------- jaximu's step


class _Captured(Exception):
    def __init__(self, fn, args):
        super().__init__("captured")
        self.fn, self.args = fn, args


def _grab(*args, **kw):
    """Stands in for ``training._step`` while :func:`train` is run to its first step."""
    raise _Captured(kw, args)


from _pypose_fix import fix_pypose_cumops  # noqa: E402


def capture_train_step(seqs, config: TrainConfig, seed: int = 0):
    """``(step, args, closure)``: the undecorated step function that
    :func:`jaximu.learning.train` builds for ``seqs`` and ``config``, the arguments of its
    first call ``((model, offsets), model, opt_state, key, G, A, Q, V, B, ...)`` (the
    second, the EMA, is the initial model), and the variables it closes over
    (``S``, ``L``, ``dt``, ``cfg``, ...) with the data arguments ``G``, ``A``, ``Q``, ``V``
    added. ``train`` is run up to its first step and
    stopped there; nothing is compiled."""
    real = training_module._step
    training_module._step = _grab
    try:
        train(seqs, config, seed=seed, log=None)
    except _Captured as c:
        kw, args = c.fn, c.args
    else:
        raise RuntimeError(
            "jaximu.learning.train no longer calls training._step: "
            "update capture_train_step in benchmarks/learning.py"
        )
    finally:
        training_module._step = real
    missing = {"cfg", "dt", "L"} - set(kw)
    if missing:
        raise RuntimeError(
            f"training._step no longer takes {sorted(missing)}: update "
            "capture_train_step in benchmarks/learning.py"
        )
    # the undecorated step with its static settings bound; the data are its arguments
    # (model, ema, opt_state, key, G, A, Q, V, B, R, noise, bias_noise, has_v, n_v), passed in
    # rather than closed over (constants folded into the program compile slowly)
    fn = functools.partial(real.__wrapped__, **kw)
    closure = dict(kw, S=args[4].shape[0])
    closure.update(zip(("G", "A", "Q", "V"), args[4:8]))
    return fn, args, closure


def _huber_only(*args, **kw):
    """``increment_loss`` without its NLL term (``bias_sigma=None``)."""
    kw["bias_sigma"] = None
    return increment_loss(*args, **kw)


def compile_step(fn, args, nll=True):
    """``(compiled, compile_s)``: ``eqx.filter_jit(fn)`` lowered and compiled ahead of time
    (tracing, lowering, XLA). Without ``nll`` the step is traced with the loss's NLL term
    left out (``increment_loss`` seen by ``train``'s loss as ``bias_sigma=None``)."""
    t0 = time.perf_counter()
    if nll:
        compiled = eqx.filter_jit(fn).lower(*args).compile()
    else:
        # a function of its own: JAX caches traces by function, and fn's was traced with
        # the NLL
        def step_without_nll(*a):
            return fn(*a)

        training_module.increment_loss = _huber_only
        try:
            compiled = eqx.filter_jit(step_without_nll).lower(*args).compile()
        finally:
            training_module.increment_loss = increment_loss
    return compiled, time.perf_counter() - t0


class JaxRunner:
    """One training step per call, chained (each step starts from the previous one's model
    and optimiser state, as in ``train``)."""

    def __init__(self, compiled, args, seed):
        self.compiled = compiled
        self.model, self.ema, self.opt_state = args[:3]
        self.data = args[4:]
        self.key = jax.random.key(seed)
        self.loss = None

    def __call__(self):
        self.key, k = jax.random.split(self.key)
        self.model, self.ema, self.opt_state, loss, parts = self.compiled(
            self.model, self.ema, self.opt_state, k, *self.data
        )
        jax.block_until_ready((self.model, self.opt_state, loss))
        self.loss, self.nll = float(loss), float(parts[1])
        return self.loss


# --------------------------------------------------------------------------- PyTorch


def torch_available():
    try:
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def pypose_available():
    try:
        import pypose  # noqa: F401
    except ImportError:
        return False
    return True


def make_torch_model(mcfg):
    """Brossard's network as PyTorch code has it: channels-first ``Conv1d``; the same layers,
    padding, activation, dropout and heads as :class:`jaximu.learning.Denoiser`."""
    import torch
    from torch import nn
    from torch.nn import functional as F

    class TorchDenoiser(nn.Module):
        def __init__(self, cfg):
            super().__init__()
            widths = (6,) + tuple(cfg.channels)
            self.convs = nn.ModuleList(
                nn.Conv1d(widths[i], widths[i + 1], cfg.kernel, dilation=d)
                for i, d in enumerate(cfg.dilations)
            )
            self.head = nn.Conv1d(widths[-1], cfg.corrections, 1)
            self.noise_head = nn.Conv1d(widths[-1], 3, 1)
            for conv in (self.head, self.noise_head):  # the untrained model: constant bias
                nn.init.zeros_(conv.weight)
                nn.init.zeros_(conv.bias)
            self.gyro_matrix = nn.Parameter(torch.zeros(3, 3))
            self.log_bias_sigma = nn.Parameter(torch.tensor(math.log(cfg.bias_sigma)))
            self.log_reference_sigma = nn.Parameter(torch.tensor(math.log(cfg.reference_sigma)))
            self.act = nn.GELU(approximate="tanh")  # jax.nn.gelu's default
            self.drop = nn.Dropout(cfg.dropout)
            f = lambda x: torch.tensor(x, dtype=torch.float32)
            for name in (
                "input_mean",
                "input_std",
                "gyro_bias",
                "accel_bias",
                "gyro_scale",
                "accel_scale",
            ):
                self.register_buffer(name, f(getattr(cfg, name)), persistent=False)
            self.cfg = cfg

        def forward(self, gyro, accel):
            """``(ω̂, â, σ_g)``, each ``(B, T, 3)``, from raw ``(B, T, 3)`` samples."""
            x = (torch.cat([gyro, accel], -1) - self.input_mean) / self.input_std
            x = x.transpose(1, 2)  # (B, 6, T)
            for conv in self.convs:
                pad = (conv.kernel_size[0] - 1) * conv.dilation[0]
                x = self.drop(self.act(conv(F.pad(x, (pad, 0), mode="replicate"))))
            y = self.head(x).transpose(1, 2)
            z = self.noise_head(x.detach()).transpose(1, 2)
            w = gyro + gyro @ self.gyro_matrix.T - self.gyro_bias + self.gyro_scale * y[..., 0:3]
            a = accel - self.accel_bias
            if self.cfg.accel_head:
                a = a + self.accel_scale * y[..., 3:6]
            density = self.cfg.gyro_density * torch.exp(3.0 * torch.tanh(z / 3.0))
            return w, a, density

    return TorchDenoiser(mcfg)


def jax_to_torch(jmodel, tmodel):
    """Copy a :class:`jaximu.learning.Denoiser`'s weights into the PyTorch model: a
    convolution's JAX weight ``(K, in, out)`` is PyTorch's ``(out, in, K)`` (both are
    cross-correlations, no flip)."""
    import torch

    pairs = list(zip(jmodel.layers, tmodel.convs)) + [
        (jmodel.head, tmodel.head),
        (jmodel.noise_head, tmodel.noise_head),
    ]
    with torch.no_grad():
        for jc, tc in pairs:
            tc.weight.copy_(torch.from_numpy(np.asarray(jc.weight).transpose(2, 1, 0).copy()))
            tc.bias.copy_(torch.from_numpy(np.asarray(jc.bias).copy()))
        tmodel.gyro_matrix.copy_(torch.from_numpy(np.asarray(jmodel.gyro_matrix).copy()))
        tmodel.log_bias_sigma.copy_(torch.tensor(float(jmodel.log_bias_sigma)))
        tmodel.log_reference_sigma.copy_(torch.tensor(float(jmodel.log_reference_sigma)))


# quaternions [w, x, y, z] (jaximu's order), batched over leading axes


def _qmul(p, q):
    import torch

    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        -1,
    )


def _qconj(q):
    import torch

    return torch.cat([q[..., :1], -q[..., 1:]], -1)


def _qnormalize(q):
    return q / q.norm(dim=-1, keepdim=True)


def _qexp(v):
    """``Exp`` of a rotation vector ``(..., 3)`` as a unit quaternion."""
    import torch

    th2 = (v * v).sum(-1, keepdim=True)
    th = torch.sqrt(th2.clamp_min(1e-30))
    small = th < 1e-4
    k = torch.where(small, 0.5 - th2 / 48.0, torch.sin(0.5 * th) / th)
    c = torch.where(small, 1.0 - th2 / 8.0, torch.cos(0.5 * th))
    return torch.cat([c, k * v], -1)


def _qlog(q):
    """``Log`` of a unit quaternion ``(..., 4)`` as a rotation vector (shortest rotation)."""
    import torch

    q = torch.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    n2 = (v * v).sum(-1, keepdim=True)
    n = torch.sqrt(n2.clamp_min(1e-30))
    w = q[..., :1]
    small = n < 1e-4
    k = torch.where(small, 2.0 / w - 2.0 * n2 / (3.0 * w**3), 2.0 * torch.atan2(n, w) / n)
    return k * v


def plain_windows(gyro, dt, H):
    """``(B, W, 4)`` ΔR̂ of windows of ``H`` samples: the product
    ``Exp(ω_0 dt) … Exp(ω_{H-1} dt)`` of each window, multiplied pairwise (log₂ H levels)."""
    if H & (H - 1):
        raise ValueError(f"plain_windows: H must be a power of two, got {H}")
    B, T = gyro.shape[:2]
    W = T // H
    q = _qexp(gyro[:, : W * H].reshape(B, W, H, 3) * dt)
    while q.shape[-2] > 1:
        q = _qmul(q[..., 0::2, :], q[..., 1::2, :])
    return _qnormalize(q[..., 0, :])


def pypose_windows(integrator, gyro, accel, dt, H):
    """``(B, W)`` ΔR̂ of windows of ``H`` samples as a PyPose ``SO3`` LieTensor, integrated by
    PyPose's ``IMUPreintegrator`` over the batch of all windows ``(B·W, H, 3)``."""
    import torch

    B, T = gyro.shape[:2]
    W = T // H
    g = gyro[:, : W * H].reshape(B * W, H, 3)
    a = accel[:, : W * H].reshape(B * W, H, 3)
    d = torch.full((B * W, H, 1), dt, dtype=gyro.dtype)
    return integrator(d, g, a)["rot"][:, -1].view(B, W, 4)


class _Quat:
    """The rotation operations of the loss on ``[w, x, y, z]`` tensors (plain PyTorch)."""

    @staticmethod
    def from_wxyz(q):
        return q

    mul = staticmethod(lambda p, q: _qnormalize(_qmul(p, q)))
    inv = staticmethod(_qconj)
    log = staticmethod(_qlog)


class _PyPose:
    """The same on PyPose ``SO3`` LieTensors (``[x, y, z, w]``). PyPose's backward passes
    are written for chains of its own operations (its gradients of a LieTensor live in the
    tangent space), so once the windows come from PyPose the loss stays in PyPose up to
    ``Log``."""

    @staticmethod
    def from_wxyz(q):
        import pypose as pp
        import torch

        return pp.SO3(torch.cat([q[..., 1:], q[..., :1]], -1))

    mul = staticmethod(lambda p, q: p * q)
    inv = staticmethod(lambda q: q.Inv())
    log = staticmethod(lambda q: q.Log().tensor())


def torch_increment_loss(
    gyro,
    accel,
    q_true,
    dt,
    horizons=(16, 32),
    *,
    huber_delta=0.005,
    weight=1e6,
    skip=0,
    integrator=None,
):
    """The Huber part of :func:`jaximu.learning.losses.increment_loss` in PyTorch: windows of
    ``horizons[0]`` samples integrated by PyPose (``integrator``) or by :func:`plain_windows`,
    longer horizons composed from pairs, ``Log(ΔR_gtᵀ ΔR̂)``, SmoothL1 of ``r/δ`` times δ²,
    horizon ``i`` weighted ``1/2^i``. ``q_true``: ``(B, T + 1, 4)`` ``[w, x, y, z]``."""
    import torch
    from torch.nn import functional as F

    H0 = horizons[0]
    if integrator is None:
        ops, dq = _Quat, plain_windows(gyro, dt, H0)
    else:
        ops, dq = _PyPose, pypose_windows(integrator, gyro, accel, dt, H0)
    loss = torch.zeros((), dtype=gyro.dtype, device=gyro.device)
    for i, H in enumerate(horizons):
        if i:
            W2 = dq.shape[-2] // 2
            dq = ops.mul(dq[:, 0 : 2 * W2 : 2], dq[:, 1 : 2 * W2 : 2])
        n = (q_true.shape[-2] - 1) // H
        ends = ops.from_wxyz(q_true[:, 0 : n * H + 1 : H])
        dq_true = ops.mul(ops.inv(ends[:, :-1]), ends[:, 1:])
        W = min(dq_true.shape[-2], dq.shape[-2])
        s = -(-skip // (2**i))
        r = ops.log(ops.mul(ops.inv(dq_true[:, s:W]), dq[:, s:W]))
        h = F.smooth_l1_loss(r / huber_delta, torch.zeros_like(r), beta=1.0)
        loss = loss + weight * huber_delta**2 * h / 2**i
    return loss


class TorchRunner:
    """The PyTorch training step: random offsets and input noise as ``train``'s step draws
    them, forward, the Huber increment loss, backward, AdamW (weight decay on the
    convolution weights, as ``train``'s mask). ``device``: where PyTorch runs (``"cuda"``
    on a GPU); ``compiled``: the forward and loss through ``torch.compile``."""

    def __init__(self, tmodel, closure, integration, seed=0, device="cpu", compiled=False):
        import torch

        cfg = closure["cfg"]
        self.torch = torch
        self.device = device
        self.model = tmodel.to(device)
        self.G, self.A, self.Q = (torch.from_numpy(np.array(closure[k])).to(device) for k in "GAQ")
        self.S, self.L, self.dt, self.cfg = closure["S"], closure["L"], closure["dt"], cfg
        self.noise = torch.tensor([cfg.gyro_noise] * 3 + [cfg.accel_noise] * 3, device=device)
        self.bias_noise = torch.tensor(
            [cfg.gyro_bias_noise] * 3 + [cfg.accel_bias_noise] * 3, device=device
        )
        decay = [p for n, p in tmodel.named_parameters() if p.ndim == 3]
        rest = [p for n, p in tmodel.named_parameters() if p.ndim != 3]
        self.opt = torch.optim.AdamW(
            [
                {"params": decay, "weight_decay": cfg.weight_decay},
                {"params": rest, "weight_decay": 0.0},
            ],
            lr=cfg.learning_rate,
        )
        self.integrator = None
        if integration == "pypose":
            import pypose as pp

            self.integrator = pp.module.IMUPreintegrator(gravity=9.81, prop_cov=False, reset=True)
        self.gen = torch.Generator(device=device).manual_seed(seed)
        self.loss = None

        def forward_loss(x, q):
            w, a, _ = self.model(x[..., :3].contiguous(), x[..., 3:].contiguous())
            return torch_increment_loss(
                w, a, q, self.dt, cfg.horizons, skip=cfg.skip, integrator=self.integrator
            )

        self.forward_loss = torch.compile(forward_loss) if compiled else forward_loss

    def __call__(self):
        torch = self.torch
        S, L, dev = self.S, self.L, self.device
        offs = torch.randint(0, self.cfg.offset, (S,), generator=self.gen, device=dev)
        idx = offs[:, None] + torch.arange(L, device=dev)[None, :]

        def take(X, i):
            return torch.gather(X, 1, i[..., None].expand(-1, -1, X.shape[-1]))

        x = torch.cat([take(self.G, idx), take(self.A, idx)], -1)
        x = (
            x
            + self.noise * torch.randn(x.shape, generator=self.gen, device=dev)
            + self.bias_noise * torch.randn((S, 1, 6), generator=self.gen, device=dev)
        )
        q = take(self.Q, torch.cat([idx, idx[:, -1:] + 1], 1))
        self.model.train()
        self.opt.zero_grad(set_to_none=True)
        loss = self.forward_loss(x, q)
        loss.backward()
        self.opt.step()
        self.loss = loss.item()
        return self.loss


def check_torch_equivalence(jmodel, closure, integration, T=None, S=2, seed=3):
    """The PyTorch model and loss against jaximu's on a small batch with the same weights:
    a JAX model with random heads and gyro matrix (so that the corrections are not zero) is
    copied into the PyTorch model; no dropout. Returns the relative differences. ``T``:
    samples per part (default: the windows the loss skips at each part's start, then four
    of the longest horizon, so every horizon has windows)."""
    import torch

    cfg = closure["cfg"]
    T = cfg.skip * cfg.horizons[0] + 4 * cfg.horizons[-1] if T is None else T
    rng = jax.random.split(jax.random.key(seed), 4)
    jm = eqx.tree_at(
        lambda m: (m.head.weight, m.head.bias, m.noise_head.weight, m.gyro_matrix),
        jmodel,
        (
            0.05 * jax.random.normal(rng[0], jmodel.head.weight.shape),
            0.05 * jax.random.normal(rng[1], jmodel.head.bias.shape),
            0.3 * jax.random.normal(rng[2], jmodel.noise_head.weight.shape),
            1e-2 * jax.random.normal(rng[3], (3, 3)),
        ),
    )
    g, a, q = closure["G"][:S, :T], closure["A"][:S, :T], closure["Q"][:S, : T + 1]
    dt = closure["dt"]

    # the tracked bias is an input of the step (computed once per recording, outside it): the
    # check gives both networks the constant one
    b = jnp.broadcast_to(jnp.asarray(jmodel.config.gyro_bias, g.dtype), g.shape)

    def jloss(m):
        c = m(g, a, gyro_bias=b)
        return increment_loss(c, q, dt, cfg.horizons, skip=cfg.skip)[0], c

    (lj, cj), gj = eqx.filter_jit(eqx.filter_value_and_grad(jloss, has_aux=True))(jm)
    tm = make_torch_model(jm.config)
    jax_to_torch(jm, tm)
    tm.eval()
    integrator = None
    if integration == "pypose":
        import pypose as pp

        integrator = pp.module.IMUPreintegrator(gravity=9.81, prop_cov=False, reset=True)
    tg, ta, tq = (torch.from_numpy(np.asarray(x).copy()) for x in (g, a, q))
    w, acc, dens = tm(tg, ta)
    lt = torch_increment_loss(w, acc, tq, dt, cfg.horizons, skip=cfg.skip, integrator=integrator)
    lt.backward()
    rel = lambda x, y: float(np.max(np.abs(x - y)) / max(np.max(np.abs(y)), 1e-30))
    grad_j = np.asarray(gj.layers[0].weight).transpose(2, 1, 0)
    return dict(
        batch=[S, T],
        gyro_rel=rel(w.detach().numpy(), np.asarray(cj.gyro)),
        density_rel=rel(dens.detach().numpy(), np.asarray(cj.gyro_density)),
        loss_jax=float(lj),
        loss_torch=float(lt.detach()),
        loss_rel=abs(float(lt.detach()) - float(lj)) / abs(float(lj)),
        grad_first_layer_rel=rel(tm.convs[0].weight.grad.numpy(), grad_j),
        integration=integration,
    )


# --------------------------------------------------------------------------- integration alone


def integration_runners(closure, integration_available):
    """Forward and gradient of jaximu's preintegration of the loss's windows, and PyPose's."""
    S, L, dt = closure["S"], closure["L"], closure["dt"]
    H = closure["cfg"].horizons[0]
    W = L // H
    g = jnp.asarray(closure["G"][:, : W * H]).reshape(S, W, H, 3)
    a = jnp.asarray(closure["A"][:, : W * H]).reshape(S, W, H, 3)
    d = jnp.asarray(dt, jnp.float32)
    weights = jnp.asarray(np.random.default_rng(0).normal(size=(S, W, 4)), jnp.float32)

    def forward(g, a):
        p = jaximu.preintegrate(g, a, d)
        return p.delta_q, p.delta_v, p.delta_p

    def scalar(g, a):
        return jnp.sum(weights * jaximu.preintegrate(g, a, d).delta_q)

    runners, compile_s = {}, {}
    for name, f in (("jaximu forward", forward), ("jaximu forward+grad", jax.grad(scalar))):
        t0 = time.perf_counter()
        c = jax.jit(f).lower(g, a).compile()
        compile_s[name] = time.perf_counter() - t0
        runners[name] = lambda c=c: jax.block_until_ready(c(g, a))
    if integration_available:
        import pypose as pp
        import torch

        integ = pp.module.IMUPreintegrator(gravity=9.81, prop_cov=False, reset=True)
        tg = torch.from_numpy(np.asarray(g).reshape(S * W, H, 3).copy())
        ta = torch.from_numpy(np.asarray(a).reshape(S * W, H, 3).copy())
        td = torch.full((S * W, H, 1), dt, dtype=torch.float32)
        tw = torch.from_numpy(np.asarray(weights).reshape(S * W, 4)[:, [1, 2, 3, 0]].copy())

        def pp_forward():
            with torch.no_grad():
                out = integ(td, tg, ta)
            return out["rot"], out["vel"], out["pos"]

        def pp_grad():  # the cost of a backward pass (PyPose's gradient of a .tensor()
            # of its LieTensor is a tangent-space one: fine for timing, not for a loss)
            gg = tg.clone().requires_grad_(True)
            out = integ(td, gg, ta)
            (out["rot"][:, -1].tensor() * tw).sum().backward()
            return gg.grad

        runners["pypose forward"] = pp_forward
        runners["pypose forward+grad"] = pp_grad
    return runners, compile_s, dict(windows=S * W, window_samples=H, samples=S * W * H)


# --------------------------------------------------------------------------- timing


def alternate(runners: dict, repeats: int, warmup: int = 1, min_round_s: float = 0.0, log=None):
    """Run each of ``runners`` (name → callable) ``warmup`` times, then ``repeats`` rounds
    of each in turn; returns name → list of seconds per call (one per round) and the time of
    each one's first call. A runner whose warm-up call took less than ``min_round_s`` is
    called that many times more per round (the round's time divided by the calls), so that
    millisecond calls are not timed one by one."""
    first, calls = {}, {}
    for name, fn in runners.items():
        for i in range(max(1, warmup)):
            t0 = time.perf_counter()
            fn()
            t = time.perf_counter() - t0
            if i == 0:
                first[name] = t
        calls[name] = max(1, math.ceil(min_round_s / max(t, 1e-6))) if min_round_s else 1
    times = {name: [] for name in runners}
    for r in range(repeats):
        for name, fn in runners.items():
            t0 = time.perf_counter()
            for _ in range(calls[name]):
                fn()
            times[name].append((time.perf_counter() - t0) / calls[name])
        if log:
            log(
                f"  round {r + 1}/{repeats}: "
                + ", ".join(f"{n} {ts[-1]:.4f} s" for n, ts in times.items())
            )
    return times, first, calls


def summarise(times, samples):
    out = {}
    for name, ts in times.items():
        med = statistics.median(ts)
        out[name] = dict(
            median_s=med, min_s=min(ts), max_s=max(ts), runs_s=ts, samples_per_s=samples / med
        )
    return out


def ratio(times, a, b):
    """``b``'s time over ``a``'s (how many times faster ``a`` is): from the medians, and the
    median and range of the per-round ratios."""
    per_round = [tb / ta for ta, tb in zip(times[a], times[b])]
    return dict(
        of_medians=statistics.median(times[b]) / statistics.median(times[a]),
        median_per_round=statistics.median(per_round),
        min_per_round=min(per_round),
        max_per_round=max(per_round),
    )


def fmt_rate(x):
    return f"{x / 1e6:.3f} M" if x >= 1e6 else f"{x / 1e3:.1f} k"


def say(*a):
    print(*a, flush=True)


# --------------------------------------------------------------------------- main


def versions():
    v = {
        "python": sys.version.split()[0],
        "jax": jax.__version__,
        "equinox": eqx.__version__,
        "numpy": np.__version__,
        "jaximu": jaximu.__version__,
    }
    for mod in ("jaxlib", "optax", "torch", "pypose"):
        try:
            v[mod] = __import__(mod).__version__
        except ImportError:
            v[mod] = None
    return v


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument(
        "--data",
        nargs="+",
        required=True,
        metavar="DIR",
        help="sequence folders with ground truth (the EuRoC training sequences)",
    )
    ap.add_argument(
        "--repeats",
        type=int,
        default=7,
        help="timed rounds of each variant, after warm-up (default 7, at least 5 "
        "for a reported figure)",
    )
    ap.add_argument("--warmup", type=int, default=2, help="untimed calls of each variant")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="smoke test: 2 repeats, 1 warm-up (figures not for reporting)",
    )
    ap.add_argument("--no-torch", action="store_true", help="leave the PyTorch rows out")
    ap.add_argument(
        "--torch-device",
        default=None,
        help="where the PyTorch step runs (default: cuda when JAX runs on a GPU and torch "
        "sees one, else cpu)",
    )
    ap.add_argument(
        "--torch-compile",
        action="store_true",
        help="also time the PyTorch step with its forward and loss through torch.compile",
    )
    ap.add_argument(
        "--torch-integration",
        choices=("auto", "pypose", "plain"),
        default="auto",
        help="how the PyTorch loss integrates its windows: PyPose's "
        "IMUPreintegrator (auto: when importable) or a plain quaternion product",
    )
    ap.add_argument(
        "--no-plain",
        action="store_true",
        help="leave out the PyTorch step with plain quaternion integration (timed "
        "beside the PyPose one: what PyPose's integration costs in the step)",
    )
    ap.add_argument(
        "--full-training",
        action="store_true",
        help="also run jaximu.learning.train with the default TrainConfig to the "
        "end (~10 min on 2 cores): wall time to the final model",
    )
    ap.add_argument(
        "--train-minutes",
        type=float,
        default=None,
        help="with --full-training: stop train after this wall time (its `minutes`)",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--out",
        default=None,
        help="JSON output path (default benchmarks/results/learning-<machine>.json)",
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.repeats, args.warmup = 2, 1
    if args.train_minutes is not None and not args.full_training:
        ap.error("--train-minutes is for --full-training")

    info = machine_info()
    vers = versions()
    say(
        f"# learning benchmark on {info['cpu_model']} ({info['cpus_usable']} usable CPUs), "
        f"jax {vers['jax']} ({jax.default_backend()}), equinox {vers['equinox']}, "
        f"torch {vers['torch']}, pypose {vers['pypose']}"
    )

    folders = [pathlib.Path(p) for p in args.data]
    t0 = time.perf_counter()
    seqs = [load_sequence(p) for p in folders]
    load_s = time.perf_counter() - t0
    say(
        f"read {len(seqs)} sequences in {load_s:.1f} s: "
        + ", ".join(f"{s.name} ({len(s)})" for s in seqs)
    )

    config = TrainConfig()
    step_fn, step_args, closure = capture_train_step(seqs, config, args.seed)
    S, L = closure["S"], closure["L"]
    samples = S * L
    say(
        f"train's step: {S} parts × {L} samples = {samples} samples per step "
        f"(windows of {config.horizons}, skip {config.skip}, offsets < {config.offset})"
    )

    doc = dict(
        benchmark="learning",
        host=machine_slug(info),
        machine=info,
        versions=vers,
        data=[str(p) for p in folders],
        sequences=[s.name for s in seqs],
        load_seconds=load_s,
        train_config=config.to_json(),
        model_config=step_args[1].config.to_json(),
        batch=dict(parts=S, samples_per_part=L, samples_per_step=samples),
        repeats=args.repeats,
        warmup=args.warmup,
        quick=args.quick,
    )

    # ---- 1. compile jaximu's step (and the no-NLL variant)
    compiled, comp = compile_step(step_fn, step_args, nll=True)
    compiled_h, comp_h = compile_step(step_fn, step_args, nll=False)
    say(f"compiled train's step in {comp:.1f} s (without NLL: {comp_h:.1f} s)")
    runners = {"jaximu step": JaxRunner(compiled, step_args, args.seed)}

    # ---- 2. the PyTorch step
    use_torch = torch_available() and not args.no_torch
    integration = None
    if not use_torch:
        say(
            "PyTorch rows skipped: "
            + ("--no-torch" if args.no_torch else "torch is not installed (pip install torch)")
        )
    else:
        import torch

        torch.set_num_threads(TORCH_THREADS)
        integration = args.torch_integration
        if integration == "auto":
            integration = "pypose" if pypose_available() else "plain"
        if integration == "pypose" and not pypose_available():
            sys.exit("--torch-integration pypose: pypose is not installed (pip install pypose)")
        if integration == "pypose" or pypose_available():
            patched = fix_pypose_cumops()
            doc["pypose_patch"] = patched
            if patched:
                say("note: " + patched)
        if integration == "plain":
            say(
                "PyTorch loss integrates its windows with plain quaternion products"
                + ("" if pypose_available() else " (pypose is not installed)")
            )
        check = check_torch_equivalence(step_args[1], closure, integration)
        rel = [check[k] for k in ("gyro_rel", "density_rel", "loss_rel")]
        # a NaN loss is no agreement (and Python's max() would pass over it)
        finite = all(np.isfinite(check[k]) for k in ("loss_jax", "loss_torch"))
        ok = bool(finite and np.all(np.isfinite(rel)) and max(rel) < CHECK_RTOL)
        check["ok"] = ok
        doc["torch_check"] = check
        say(
            f"check, PyTorch against jaximu (same weights, batch {check['batch']}, float32, "
            f"{integration} integration): corrected gyro {check['gyro_rel']:.1e}, density "
            f"{check['density_rel']:.1e}, loss {check['loss_torch']:.6g} vs "
            f"{check['loss_jax']:.6g} ({check['loss_rel']:.1e}); first-layer gradient "
            f"{check['grad_first_layer_rel']:.1e} (max relative differences) -> "
            + ("agree" if ok else f"DIFFER (tolerance {CHECK_RTOL:g})")
        )
        tmodel = make_torch_model(step_args[1].config)
        jax_to_torch(step_args[1], tmodel)  # the same initial weights as jaximu's step
        tdev = args.torch_device or (
            "cuda" if jax.default_backend() == "gpu" and torch.cuda.is_available() else "cpu"
        )
        doc["torch_device"] = tdev
        runners["torch step"] = TorchRunner(tmodel, closure, integration, args.seed, tdev)
        if args.torch_compile:
            tcomp = make_torch_model(step_args[1].config)
            jax_to_torch(step_args[1], tcomp)
            runners["torch step, torch.compile"] = TorchRunner(
                tcomp, closure, integration, args.seed, tdev, compiled=True
            )
    runners["jaximu step without NLL"] = JaxRunner(compiled_h, step_args, args.seed)
    if use_torch and integration == "pypose" and not args.no_plain:
        # what PyPose's integration costs inside the PyTorch step: the same step with the
        # windows integrated by plain quaternion products
        tplain = make_torch_model(step_args[1].config)
        jax_to_torch(step_args[1], tplain)
        runners["torch step, plain integration"] = TorchRunner(tplain, closure, "plain", args.seed)

    say(f"timing the training steps: {args.warmup} warm-up + {args.repeats} alternating rounds")
    meter = CpuMeter()
    times, first, _ = alternate(runners, args.repeats, args.warmup, log=say)
    other = meter.other_share()
    steps = summarise(times, samples)
    for name in steps:
        steps[name]["first_call_s"] = first[name]
        steps[name]["final_loss"] = runners[name].loss
        if isinstance(runners[name], JaxRunner):
            steps[name]["final_nll"] = runners[name].nll
    if (
        steps["jaximu step without NLL"]["final_nll"] != 0.0
        or steps["jaximu step"]["final_nll"] == 0.0
    ):
        raise AssertionError(
            "the step without NLL still computes it (or the step with it "
            "does not): capture_train_step/compile_step no longer apply"
        )
    steps["jaximu step"]["compile_s"] = comp
    steps["jaximu step without NLL"]["compile_s"] = comp_h
    ratios = {}
    if "torch step" in steps:
        ratios["jaximu step vs torch"] = ratio(times, "jaximu step", "torch step")
        ratios["jaximu step without NLL vs torch"] = ratio(
            times, "jaximu step without NLL", "torch step"
        )
    if "torch step, torch.compile" in steps:
        ratios["jaximu step without NLL vs torch.compile"] = ratio(
            times, "jaximu step without NLL", "torch step, torch.compile"
        )
    if "torch step, plain integration" in steps:
        ratios["jaximu step without NLL vs torch, plain integration"] = ratio(
            times, "jaximu step without NLL", "torch step, plain integration"
        )
        ratios["torch plain integration vs pypose"] = ratio(
            times, "torch step, plain integration", "torch step"
        )
    ratios["jaximu NLL cost"] = ratio(times, "jaximu step without NLL", "jaximu step")
    doc["training_step"] = dict(
        samples_per_step=samples,
        cases=steps,
        ratios=ratios,
        other_cpu_share=other,
        torch_integration=integration,
        torch_threads=TORCH_THREADS if use_torch else None,
    )

    # ---- 3. the integration alone
    pp_ok = use_torch and pypose_available()
    if not pp_ok:
        say(
            "PyPose rows skipped: "
            + ("no torch" if not use_torch else "pypose is not installed (pip install pypose)")
        )
    irunners, icomp, ishape = integration_runners(closure, pp_ok)
    say(
        f"timing the integration of {ishape['windows']} windows × {ishape['window_samples']} "
        f"samples: {args.warmup} warm-up + {args.repeats} alternating rounds"
    )
    meter = CpuMeter()
    itimes, ifirst, icalls = alternate(
        irunners, args.repeats, args.warmup, min_round_s=0.3, log=say
    )
    iother = meter.other_share()
    integ = summarise(itimes, ishape["samples"])
    for name in integ:
        integ[name]["first_call_s"] = ifirst[name]
        integ[name]["calls_per_round"] = icalls[name]
        if name in icomp:
            integ[name]["compile_s"] = icomp[name]
    iratios = {}
    if pp_ok:
        iratios["forward"] = ratio(itimes, "jaximu forward", "pypose forward")
        iratios["forward+grad"] = ratio(itimes, "jaximu forward+grad", "pypose forward+grad")
    doc["integration"] = dict(
        **ishape,
        cases=integ,
        ratios=iratios,
        other_cpu_share=iother,
        target_vs_pypose=INTEGRATION_TARGET,
    )

    # ---- report (written before the whole training, which takes long)
    say("\n| workload | variant | samples/s | median s | range s | first call s | compile s |")
    say("|---|---|--:|--:|--:|--:|--:|")
    for wl, cases in (("training step", steps), ("integration", integ)):
        for name, c in cases.items():
            comp_txt = f"{c['compile_s']:.1f}" if "compile_s" in c else "-"
            say(
                f"| {wl} | {name} | {fmt_rate(c['samples_per_s'])} | {c['median_s']:.3f} | "
                f"{c['min_s']:.3f}–{c['max_s']:.3f} | {c['first_call_s']:.2f} | {comp_txt} |"
            )
    say(
        f"\ntraining step: {S} × {L} = {samples} samples; other processes used "
        f"{100 * (other or 0):.0f} % of the CPUs while it was timed"
    )
    for name, r in ratios.items():
        say(
            f"- {name}: {r['of_medians']:.2f}× (per round {r['median_per_round']:.2f}×, "
            f"{r['min_per_round']:.2f}–{r['max_per_round']:.2f})"
        )
    say(
        f"integration: {ishape['windows']} windows × {ishape['window_samples']} samples; other "
        f"processes used {100 * (iother or 0):.0f} % of the CPUs"
    )
    for name, r in iratios.items():
        verdict = "met" if r["of_medians"] >= INTEGRATION_TARGET else "missed"
        say(
            f"- jaximu vs PyPose, {name}: {r['of_medians']:.2f}× (per round "
            f"{r['median_per_round']:.2f}×, {r['min_per_round']:.2f}–{r['max_per_round']:.2f}); "
            f"target ≥ {INTEGRATION_TARGET:g}×: {verdict}"
        )
    if any(x is not None and x > 0.10 for x in (other, iother)):
        say(
            "note: other processes used more than 10 % of the CPUs: the figures are lower "
            "bounds, and the ratios less certain than on a quiet machine"
        )

    out = (
        pathlib.Path(args.out)
        if args.out
        else (
            HERE / "results" / f"learning-{machine_slug(info)}{'-quick' if args.quick else ''}.json"
        )
    )
    out.parent.mkdir(parents=True, exist_ok=True)

    def save():
        out.write_text(json.dumps(doc, indent=1) + "\n")
        say(f"\nwrote {out}")

    if args.full_training:
        doc["full_training"] = {"status": "running (the process ended before train returned)"}
    save()

    # ---- 4. the whole training run (opt-in)
    if args.full_training:
        say(
            "running jaximu.learning.train (default TrainConfig"
            + (f", minutes={args.train_minutes:g}" if args.train_minutes else "")
            + ")"
        )
        meter = CpuMeter()
        t0 = time.perf_counter()
        result = train(
            seqs, config, seed=args.seed, minutes=args.train_minutes, log=lambda s: say("  " + s)
        )
        wall = time.perf_counter() - t0
        rec = result.record
        best = next((h for h in rec["history"] if h["step"] == rec["best_step"]), None)
        doc["full_training"] = dict(
            wall_s=wall,
            train_wall_s=rec["wall_seconds"],
            compile_s=rec["compile_seconds"],
            stage_s=rec["stage_seconds"],
            steps_run=rec["steps_run"],
            cut_short=rec["cut_short"],
            best_step=rec["best_step"],
            minutes=args.train_minutes,
            other_cpu_share=meter.other_share(),
            validation=[
                dict(
                    sequence=n,
                    constant_bias_deg=c,
                    learned_deg=(best["validation_aoe_mean_deg"][i] if best else None),
                )
                for i, (n, c) in enumerate(
                    zip(rec["sequences"], rec["validation_constant_bias_deg"])
                )
            ],
            validation_mean_learned_deg=(
                rec["validation_aoe_mean_deg"]
                if math.isfinite(rec["validation_aoe_mean_deg"])
                else None
            ),  # inf: cut before any validation
            history=rec["history"],
        )

    if "full_training" in doc:
        ft = doc["full_training"]
        say(
            f"\nfull training: {ft['steps_run']} steps, wall {ft['train_wall_s']:.0f} s to the "
            f"final model (of which compile ≈ {ft['compile_s']:.1f} s; with the benchmark's "
            f"overhead {ft['wall_s']:.0f} s); best step {ft['best_step']}"
            + (" (cut short by --train-minutes)" if ft["cut_short"] else "")
        )
        say("| sequence | constant bias AOE ° | learned AOE ° |\n|---|--:|--:|")
        for v in ft["validation"]:
            ld = "-" if v["learned_deg"] is None else f"{v['learned_deg']:.2f}"
            say(f"| {v['sequence']} | {v['constant_bias_deg']:.2f} | {ld} |")
        cb = float(np.mean([v["constant_bias_deg"] for v in ft["validation"]]))
        lm = ft["validation_mean_learned_deg"]
        say(f"| mean | {cb:.2f} | {'-' if lm is None else f'{lm:.2f}'} |")
        save()


if __name__ == "__main__":
    main()
