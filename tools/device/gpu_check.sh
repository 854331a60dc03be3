#!/bin/bash
# The refinement's CUDA path on a lent GPU machine: tests/refine/test_refine_cuda.py (with the CPU
# tests of the energy beside it), bench/refine_speed.py on the GPU beside the same machine's CPU (20
# iterations, one run, as a ratio) and on the GPU alone at the default iterations.
# Needs .dev/ from tools/device/gpu_payload.sh (carried). NO_BENCH=1: the tests only; PYTEST_ARGS: other tests.
cd "$(dirname "$0")/../.." || exit 1
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; LOG=$OUT/run.log
mkdir -p /tmp/sys && for f in .dev/debs/*.deb; do dpkg -x "$f" /tmp/sys; done
export LD_LIBRARY_PATH=/tmp/sys/usr/lib/x86_64-linux-gnu:/tmp/sys/lib/x86_64-linux-gnu:${LD_LIBRARY_PATH:-}
so=.dev/site/open3d/cpu/pybind.cpython-312-x86_64-linux-gnu.so
[ -f $so ] || python3 -c "import lzma,shutil,sys; shutil.copyfileobj(lzma.open(sys.argv[1]+'.xz'), open(sys.argv[1],'wb'), 1<<24)" $so
# headless/: Open3D imported without its viewers (see its sitecustomize.py).
export PYTHONPATH=$PWD:$PWD/tools/device/headless:$PWD/.dev/site PYTHONUNBUFFERED=1
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; nproc; } 2>&1 | tee "$LOG"
python3 -c "import torch, open3d, pydantic, cv2, scipy; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'open3d', open3d.__version__)" 2>&1 | tee -a "$LOG"
python3 -c "import open3d" || exit 1
python3 -m pytest -p no:cacheprovider -q -o addopts="-ra --timeout=300" ${PYTEST_ARGS:-tests/refine/test_refine_cuda.py tests/refine/test_refine_energy.py} 2>&1 | tail -n 30 | tee -a "$LOG"
[ "${NO_BENCH:-0}" = 1 ] && exit 0
echo "== refine_speed --device cuda --peer cpu --max-iterations 20" | tee -a "$LOG"
timeout 420 python3 bench/refine_speed.py --device cuda --peer cpu --max-iterations 20 --results refine_speed_gpu \
  --out "$OUT/refine_speed_gpu.json" 2>>"$OUT/errors.log" | tee -a "$LOG"
echo "== refine_speed --device cuda (default iterations)" | tee -a "$LOG"
timeout 200 python3 bench/refine_speed.py --device cuda --results refine_speed_cuda \
  --out "$OUT/refine_speed_cuda.json" 2>>"$OUT/errors.log" | tee -a "$LOG"
