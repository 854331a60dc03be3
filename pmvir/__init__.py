"""pmvir: polarimetric multi-view inverse rendering from colour-polarization captures."""

import os

__version__ = "0.1.0"

# OpenMP threads (PyTorch's, Open3D's) sleep while they wait for work instead of spinning: on a
# loaded machine the spinning threads take the cores from the ones with work (the refinement's
# energy and gradient: 35-40 % less CPU time with 2 threads at load 15). Set before any of those
# libraries loads; a value the environment already holds is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
