"""Import first to make OpenMP threads sleep between parallel regions (``OMP_WAIT_POLICY=PASSIVE``).

Set unless the variable is already set, before numba or torch start OpenMP: spinning threads
burned 2-4x the CPU time of the renderer's binning stage on a shared, oversubscribed machine and
sleeping ones cost nothing measurable on an idle one. :mod:`gscodec_shac.render` and the encoder
(its PLAS sort: 17.5 s of CPU spinning, 15.3 s sleeping, for one 1M sort on two threads) import this;
modules that need only torch (the deformation network) import this alone, without the renderer's
numba kernels.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
