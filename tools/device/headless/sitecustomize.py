"""Open3D without its viewers, for a machine that has neither X11/GL viewers' Python packages nor Open3D-ML.

``import open3d`` imports ``open3d.visualization`` (plotly, dash, an X11 window) and
``open3d.ml`` at import time; pmvir uses neither, only geometry and ray casting. Python
runs this module at start-up when its folder is on ``PYTHONPATH`` (``gpu_check.sh`` puts
it there): it registers both as empty modules, so ``import open3d`` finds them already
imported and the installed Open3D stays as its wheel shipped it.
"""

import sys
import types

for _name in ("open3d.visualization", "open3d.ml"):
    sys.modules.setdefault(_name, types.ModuleType(_name))
