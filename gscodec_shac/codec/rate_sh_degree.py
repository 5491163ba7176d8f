"""The per-Gaussian SH degree as a rate-control choice: which energy bar leaves Gaussians DC-only.

A bar ``B`` (rate point ``sh.dc_only_energy``, :mod:`.sh_degree`) codes DC-only the Gaussians of
least view-dependent energy that together hold at most the share ``B`` of it. For the rate
controller (:mod:`.rate_control`) a bar changes the SH attribute in three ways, each measured
at fit time rather than assumed:

* **bytes**: the SH planes hold the other Gaussians only. Encodes of the probe with the bar at
  :data:`RATIO_QPS` give the ratio of its SH bytes (features and side information) to the
  probe's without it at those QPs; the SH rate curve is scaled by that ratio, interpolated
  linearly in the QP between them (the end values beyond), and the flags chunk is added (its
  exact size on the whole cloud). The ratio falls towards fine QPs, where the codec spends
  bytes on the noise of near-zero coefficients (bonsai, bar 0.01: 0.87 on the probe at QP 30,
  0.73 in a whole encode at QP 17);
* **coding error**: the coded Gaussians keep the SH error they had (the SH error curve is not
  scaled). A ratio measured like the bytes one (the rendered error of the probe's coded
  Gaussians as decoded with the bar, against the probe decoded without it) came out below 1 but
  did not show in whole encodes: at the same QPs the bar cost the chair 0.3-0.4 dB and bonsai
  0.35-1.2 dB against the uncompressed model, about the zeroing error alone
  (docs/rate_control.md, "Controller version 7");
* **zeroing error**: for every pruning candidate of the controller, the rendered MSE added by
  zeroing the AC coefficients of the Gaussians the bar flags among the kept ones, by exact
  renders. Per pruning candidate, because the bar is a share of the kept Gaussians' energy:
  after pruning the faint Gaussians it takes visible ones.

So the SH attribute's predicted bytes are ``bytes_ratio(qp) * R_sh(qp) + flags`` and its rendered
MSE ``k_sh e_sh(qp) + zeroed_mse[prune]`` (the sum model of the controller,
whose other attributes are unchanged).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from gscodec_shac.codec import sh_degree as degrees
from gscodec_shac.gaussians import GaussianCloud

#: Candidate energy bars (rate point ``sh.dc_only_energy``); 0 codes every Gaussian's AC.
DC_ONLY_BARS = (0.0, 0.01)
#: Probe QPs (of the controller's ``PROBE_QPS``) at which a bar's ratios are measured.
RATIO_QPS = (18, 30)


@dataclass(frozen=True)
class DcOnlyChoice:
    """One candidate bar and what it does to the SH attribute (see module docstring)."""

    bar: float
    share: float = 0.0  # of the whole cloud's Gaussians left DC-only
    qps: tuple[int, ...] = (0,)  # where the ratios were measured
    bytes_ratios: tuple[float, ...] = (1.0,)
    zeroed_mse: tuple[float, ...] = ()  # per pruning candidate of the controller (none: 0)
    flag_bytes: float = 0.0

    def zeroing(self, prune: int) -> float:
        """The rendered MSE the bar adds under the controller's pruning candidate ``prune``."""
        return self.zeroed_mse[prune] if self.zeroed_mse else 0.0

    def bytes_factor(self, qp: np.ndarray | int) -> np.ndarray:
        """The factor of the SH bytes at base QP ``qp`` (linear between the measured QPs, the end
        values beyond)."""
        return np.interp(qp, self.qps, self.bytes_ratios)

    def rate_point_fields(self) -> dict[str, float]:
        """The bar as rate-point overrides (nothing for bar 0: the template's own setting stays)."""
        return {"dc_only_energy": self.bar} if self.bar > 0 else {}


def cloud_energy(cloud: GaussianCloud) -> np.ndarray:
    """(N,) each Gaussian's view-dependent energy as the bars rank it: AC energy times opacity (the
    encoder's default weight, :func:`.sh_degree.ac_energy`; row by row, so a subset's is its rows')."""
    return degrees.ac_energy(cloud.ac_matrix(), cloud.activated_opacities())


def whole_cloud_flags(cloud: GaussianCloud, bar: float) -> np.ndarray:
    """(N,) bool: the Gaussians the bar leaves DC-only (:func:`cloud_energy`)."""
    return degrees.dc_only_flags(cloud_energy(cloud), 0.0, bar)


def kept_flags(energy: np.ndarray, kept: np.ndarray, bar: float, order: np.ndarray) -> np.ndarray:
    """The rows of ``kept`` (ascending) the bar leaves DC-only in ``cloud.select(kept)``, given the whole
    cloud's :func:`cloud_energy`: ``kept[whole_cloud_flags(cloud.select(kept), bar)]`` (ascending).
    ``order``: ``np.argsort(energy, kind="stable")``, ranked once for every pruning choice (the kept rows
    in that order are the order of their own energies, ties by row, as sorting them anew gives)."""
    listed = np.zeros(energy.size, dtype=np.bool_)
    listed[kept] = True
    ranked = order[listed[order]]
    return np.sort(ranked[: degrees.bar_count(energy[ranked], bar)])


def fit_choices(
    without: Mapping[int, float],
    flags_of: Mapping[float, np.ndarray],
    probe_bytes: Mapping[tuple[float, int], float],
    zeroing_errors: Callable[[float], tuple[float, ...]],
    bars: tuple[float, ...] = DC_ONLY_BARS,
    bar: Any = None,
) -> list[DcOnlyChoice]:
    """The measured :class:`DcOnlyChoice` of every bar in ``bars`` (bar 0 first, unchanged).

    ``without``: the SH bytes of the probe without a bar at each of :data:`RATIO_QPS` (the rate
    model's own probe encodes); ``flags_of``: each bar's :func:`whole_cloud_flags`;
    ``probe_bytes[(bar, qp)]``: the probe's SH bytes with the bar, scaled alike (for each bar that
    flags something); ``zeroing_errors(bar)``: the zeroing error under each pruning candidate
    (``bar``: a progress bar advanced once per bar)."""
    out = [DcOnlyChoice(0.0)]
    if not any(value > 0 for value in bars):
        return out
    for value in bars:
        if value <= 0:
            continue
        flags = flags_of[value]
        if flags.any():
            measured = [probe_bytes[(value, qp)] for qp in RATIO_QPS]
            out.append(DcOnlyChoice(
                bar=value, share=float(flags.mean()), qps=RATIO_QPS,
                bytes_ratios=tuple(b / max(without[q], 1e-9) for b, q in zip(measured, RATIO_QPS)),
                zeroed_mse=tuple(zeroing_errors(value)),
                flag_bytes=float(len(degrees.flags_chunk(flags)[0]))))
        if bar is not None:
            bar.update(1)
    return out
