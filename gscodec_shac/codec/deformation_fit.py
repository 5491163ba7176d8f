"""Rounding the deformation network's weights to per-row grids: plain, and aware of the outputs (encoder only).

Plain rounding (:func:`quantise_rows`) puts every weight on the
nearest point of its row's grid ``lo + code * step`` independently. The encoder also has what
the network is evaluated on, the canonical centres ``x`` at times ``t``, so it can pick the codes
that keep each layer's *output* close instead (GPTQ, Frantar et al., 2023, applied per layer):
with the layer's inputs ``X`` (rows: one Gaussian at one time) and ``H = X^T X``, the weights of a
row are rounded one input column at a time, and the rounding error of column ``j`` is pushed onto
the columns not rounded yet through the upper Cholesky factor ``U`` of ``H^-1``:

    e_j = (w_j - q_j) / U_jj,      w_k <- w_k - e_j * U_jk   (k > j)

which is the least-squares update of the remaining weights given column ``j``'s choice. After a
matrix is rounded its bias absorbs the mean output shift, ``b <- b + (W - Q) mean(X)`` (biases
are stored as float16 in every form). The decoder reads the same ``lo + code * step`` as before.

Calibration inputs: :data:`CAL_POINTS` canonical centres (a fixed-seed sample) at
:data:`CAL_TIMES` evenly spaced times in [0, 1]; each layer's inputs come from the network in
which the layers before it are already quantised, so later layers correct earlier ones' error.
"""

from __future__ import annotations

import numpy as np

from gscodec_shac.deform_arch import DeformArch, weight_shapes
from gscodec_shac.errors import ModelFormatError

CAL_POINTS = 4096
CAL_TIMES = 16
#: Ridge added to ``H``'s diagonal, relative to its mean diagonal (keeps ``H`` invertible).
DAMPING = 0.01


def quantise_rows(value: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lo, step, codes)`` of a matrix, per row: ``lo`` and ``step`` float16, ``codes`` uint8 in 0..2^bits-1.

    ``lo`` and ``step`` are rounded to float16 first and the codes computed from the rounded
    values, so the decoder's ``lo + code * step`` is what the encoder measured."""
    top = (1 << bits) - 1
    lo = value.min(axis=1).astype(np.float16)
    span = value.max(axis=1) - lo.astype(np.float32)
    step = (span / top).astype(np.float16)
    short = step.astype(np.float32) * top < span  # rounded down: one float16 unit up covers the row
    step[short] = np.nextafter(step[short], np.float16(np.inf))
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(step))):
        raise ModelFormatError("deformation network: a weight beyond the float16 range cannot be coded")
    safe = np.where(step > 0, step.astype(np.float32), 1.0)[:, None]
    codes = np.clip(np.rint((value - lo.astype(np.float32)[:, None]) / safe), 0, top).astype(np.uint8)
    return lo, step, codes


def fitted_codes(arch: DeformArch, weights: dict[str, np.ndarray], means: np.ndarray, bits: dict[str, int],
                 seed: int = 0) -> tuple[dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], dict[str, np.ndarray]]:
    """``({matrix name: (lo, step, codes)}, {bias name: corrected bias})`` with ``bits[name]``-bit codes
    per matrix. ``means``: the canonical centres (N >= 1, 3) the network is evaluated at."""
    import torch

    from gscodec_shac.deform import DeformNetwork

    net = DeformNetwork(arch)
    net.load_weights({k: np.asarray(v, dtype=np.float32) for k, v in weights.items()})
    net = net.double()
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(means), size=min(CAL_POINTS, len(means)), replace=False)
    x = torch.from_numpy(np.asarray(means, dtype=np.float64)[np.sort(pick)])
    times = (np.arange(CAL_TIMES) + 0.5) / CAL_TIMES
    modules = dict(net.named_modules())
    codes: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    biases: dict[str, np.ndarray] = {}
    for name, shape in weight_shapes(arch):
        if len(shape) != 2:
            continue
        layer = modules[name.rsplit(".", 1)[0]]
        gram, mean = _layer_statistics(net, layer, x, times)
        w = layer.weight.detach().numpy().astype(np.float64)
        lo, step, code = gptq_rows(w, gram, bits[name])
        q = lo.astype(np.float64)[:, None] + code * step.astype(np.float64)[:, None]
        bias = layer.bias.detach().numpy() + (w - q) @ mean
        with torch.no_grad():  # later layers see this one quantised
            layer.weight.copy_(torch.from_numpy(q.astype(np.float16).astype(np.float64)))
            layer.bias.copy_(torch.from_numpy(bias.astype(np.float16).astype(np.float64)))
        codes[name] = (lo, step, code)
        biases[name.rsplit(".", 1)[0] + ".bias"] = bias.astype(np.float32)
    return codes, biases


class _Reached(Exception):
    """Raised by the statistics hook: the layers after the one measured need not run."""


def _layer_statistics(net, layer, x, times) -> tuple[np.ndarray, np.ndarray]:
    """(``X^T X / n``, ``mean(X)``) of ``layer``'s inputs over the calibration points and times."""
    import torch

    width = layer.weight.shape[1]
    gram, total, count = torch.zeros(width, width, dtype=torch.float64), torch.zeros(width, dtype=torch.float64), 0

    def hook(_module, inputs, _output) -> None:
        nonlocal gram, total, count
        value = inputs[0].reshape(-1, width)
        gram, total, count = gram + value.T @ value, total + value.sum(dim=0), count + value.shape[0]
        raise _Reached

    handle = layer.register_forward_hook(hook)
    try:
        with torch.no_grad():
            for t in times:
                try:
                    net(x, float(t))
                except _Reached:
                    pass
    finally:
        handle.remove()
    return (gram / max(count, 1)).numpy(), (total / max(count, 1)).numpy()


def gptq_rows(w: np.ndarray, gram: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lo, step, codes)`` of matrix ``w`` (out, in) on :func:`quantise_rows`' per-row grid, rounded
    column by column with the error pushed forward through ``H = gram`` (module docstring)."""
    top = (1 << bits) - 1
    lo, step, _ = quantise_rows(w.astype(np.float32), bits)
    lo64, step64 = lo.astype(np.float64), step.astype(np.float64)
    safe = np.where(step64 > 0, step64, 1.0)
    h = np.array(gram, dtype=np.float64)
    dead = np.diag(h) <= 0
    h[dead, dead] = 1.0  # an input that is always zero: its weights do not matter, round them plainly
    h += DAMPING * np.mean(np.diag(h)) * np.eye(len(h))
    upper = np.linalg.cholesky(np.linalg.inv(h)).T
    work = np.array(w, dtype=np.float64)
    codes = np.empty(w.shape, dtype=np.uint8)
    for j in range(w.shape[1]):
        code = np.clip(np.rint((work[:, j] - lo64) / safe), 0, top)
        codes[:, j] = code
        error = (work[:, j] - (lo64 + code * step64)) / upper[j, j]
        work[:, j + 1:] -= error[:, None] * upper[j, j + 1:][None, :]
    return lo, step, codes
